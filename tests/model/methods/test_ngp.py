"""The hash-grid family (model/methods/ngp.py) trains wherever the Switch-NeRF methods do: through
`leco train` under each of its three samplers, through the API and a dispatcher on SQLite and
PostgreSQL, and from a checkpoint after a kill; its sizes reach the memory check."""

import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from cli.main import main
from model.memory_estimate import describe, estimate_peak_bytes
from model.methods import family_of, get_method
from model.sizes import level_resolutions
from tests.helpers import ON_POSTGRESQL, ROOT, api_client, wait_for
from tests.workers.train.test_training import read_metrics
from workers.config import TrainConfig
from workers.models import build_models, build_optimizer

FAMILY = ["ngp", "ngp-leco", "ngp-prop", "ngp-leco-prop"]


def test_the_family_is_four_samplers_of_one_field():
    assert family_of("ngp-leco") == FAMILY and "ngp" not in family_of("leco")
    profile = TrainConfig(method="ngp", profile="cpu").resolved_profile()
    mains = {get_method(m)(profile).main_components(40)["main.hash_tables"] for m in FAMILY}
    assert len(mains) == 1  # the same field under every sampler
    # cpu: 8 levels of at most 2^16 entries x 2 features; the coarse levels need fewer
    assert 500_000 < mains.pop() <= 8 * 2**16 * 2


def resolved(method: str, profile: str = "cpu", **overrides):
    return TrainConfig(method=method, profile=profile, overrides=overrides).resolved_profile()


def test_ngp_leco_reads_its_own_sections_and_leco_keeps_the_mlps():
    def sampler(p) -> tuple:
        g = p.guided
        keys = (g.placement, g.placement_in_phase1, g.coarse_samples, g.split, g.dilate)
        return (*keys, g.online_warmup, g.main_samples, p.occupancy.budget_share)

    # cpu: 64 bins kept or dropped, 2 even samples a kept bin and its neighbours, O online from
    # main step 250, phase 1 at 8% of the budget; the MLP's LeCO keeps O's placement
    assert sampler(resolved("ngp-leco")) == (False, False, 64, 2, 1, 250, 42, 0.08)
    assert sampler(resolved("leco")) == (True, True, 16, 4, 1, 500, 21, 0.15)
    assert sampler(resolved("ngp-prop")) == sampler(resolved("leco"))
    # a job sets ngp-leco's sampler in its section; leco's is untouched by it, and the reverse
    own = {"ngp_leco.guided.split": 3, "ngp_leco.occupancy.budget_share": 0.2}
    assert (resolved("ngp-leco", **own).guided.split, resolved("leco", **own).guided.split) == (
        3,
        4,
    )
    assert resolved("ngp-leco", **own).occupancy.budget_share == 0.2
    # leco's sections are not ngp-leco's: a job that sets them for it is told where its own are
    with pytest.raises(ValueError, match="set 'ngp_leco.guided.split' instead"):
        resolved("ngp-leco", **{"guided.split": 3})
    with pytest.raises(ValueError, match="set 'ngp_leco.occupancy.budget_share' instead"):
        resolved("ngp-leco", **{"occupancy.budget_share": 0.2})
    # the paper profile: NGP+Ours samples as the paper's LeCO does
    assert sampler(resolved("ngp-leco", "paper")) == sampler(resolved("leco", "paper"))
    with pytest.raises(ValueError, match="ngp_leco.guided.split"):
        resolved("ngp-leco", **{"ngp_leco.guided.split": 0})


def test_the_sweep_and_the_memory_check_read_ngp_lecos_own_count():
    from bench.variants import sweep

    def placing(method: str, n: int = 30):
        section = "ngp_leco.guided" if method == "ngp-leco" else "guided"
        return resolved(method, **{f"{section}.main_samples": n, f"{section}.placement": True})

    points = {v.name: v.overrides for v in sweep(["ngp-leco", "leco"], placing)}
    assert points["ngp-leco-sweep-rich"] == {"ngp_leco.guided.main_samples": 60}
    assert points["leco-sweep-rich"] == {"guided.main_samples": 60}
    main_phase = lambda n: get_method("ngp-leco").memory(placing("ngp-leco", n), 40)["main"]
    assert main_phase(60).samples_per_ray == 60 and main_phase(30).samples_per_ray == 30


def test_the_hash_grid_trains_with_instant_ngps_adam_and_only_it(tiny_scene):
    def adam(method: str, phase: str, **overrides) -> dict:
        config = TrainConfig(method=method, profile="smoke", overrides=overrides)
        built = get_method(method)(config.resolved_profile())
        models = build_models(built, tiny_scene.num_images, tiny_scene.bounds.aabb, 0)
        group = build_optimizer(built, models, phase).optimizer.param_groups[0]
        return {"betas": tuple(group["betas"]), "eps": group["eps"]}

    instant_ngp = {"betas": (0.9, 0.99), "eps": 1e-15}
    pytorch = {"betas": (0.9, 0.999), "eps": 1e-8}
    assert adam("ngp", "main") == adam("ngp-prop", "main") == instant_ngp
    assert adam("ngp-leco", "main") == instant_ngp
    # LeCO's phase 1 trains its occupancy network, an MLP, and the Switch-NeRF rows keep theirs
    assert adam("ngp-leco", "occupancy") == adam("leco", "main") == adam("prop", "main") == pytorch
    assert adam("ngp", "main", **{"ngp.adam_eps": 1e-8, "ngp.adam_beta2": 0.999}) == pytorch


@pytest.mark.parametrize("method", FAMILY)
def test_an_mlp_far_field_trains_at_the_mlps_rate_beside_the_hash_tables(method, tiny_scene):
    """ngp.background=mlp: the Switch-NeRF methods' background in place of the contracted hash
    grid, in its own Adam group whose rate follows the schedule at profile.lr / ngp.lr of it."""
    from model.fields.background import BackgroundField
    from model.fields.ngp import NGPBackground

    def built(**overrides):
        config = TrainConfig(method=method, profile="smoke", overrides=overrides)
        m = get_method(method)(config.resolved_profile())
        models = build_models(m, tiny_scene.num_images, tiny_scene.bounds.aabb, 0)
        return m, models, build_optimizer(m, models, "main")

    m, models, objects = built()
    assert isinstance(models.background, NGPBackground)
    assert [g["lr_scale"] for g in objects.optimizer.param_groups] == [1.0]
    assert not models.background.sky_at_infinity
    # background.sky_at_infinity reaches whichever far field the profile builds
    for far_field in ("hash", "mlp"):
        sky = {"ngp.background": far_field, "background.sky_at_infinity": True}
        assert built(**sky)[1].background.sky_at_infinity
    m, models, objects = built(**{"ngp.background": "mlp"})
    assert isinstance(models.background, BackgroundField)
    main, far = objects.optimizer.param_groups
    assert main["lr_scale"] == 1.0 and far["lr_scale"] == pytest.approx(
        m.profile.lr / m.profile.ngp.lr
    )
    assert {id(p) for p in far["params"]} == {id(p) for p in models.background.parameters()}
    assert not {id(p) for p in far["params"]} & {id(p) for p in main["params"]}
    assert len(main["params"]) + len(far["params"]) == len(objects.params)


@pytest.mark.parametrize("method", FAMILY)
def test_each_sampler_trains_with_the_mlp_far_field_the_sky_at_infinity_and_the_distortion_loss(
    method, tiny_scene, tmp_path
):
    out = tmp_path / "run"
    args = ["train", "--scene", str(tiny_scene.root), "--method", method, "--profile", "smoke"]
    args += ["--out", str(out), "--backend", "local", "--set", "main_steps=6"]
    args += ["--set", "ngp.background=mlp", "--set", "ngp.distortion_weight=0.01"]
    args += ["--set", "background.sky_at_infinity=true"]
    assert main(args) == 0
    logged = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    distortion = [r["distortion_loss"] for r in logged if "distortion_loss" in r]
    assert distortion and all(0 < d < 1 for d in distortion)
    assert 5 < json.loads((out / "summary.json").read_text())["val"]["psnr"] < 60


@pytest.mark.parametrize("method", FAMILY)
def test_each_sampler_trains_the_hash_grid_through_leco_train(method, tiny_scene, tmp_path, capsys):
    out = tmp_path / "run"
    args = ["train", "--scene", str(tiny_scene.root), "--method", method, "--profile", "smoke"]
    args += ["--out", str(out), "--backend", "local", "--set", "main_steps=12"]
    assert main(args) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["method"] == method and summary["steps"]["phases"]["main"] == 12
    assert 5 < summary["val"]["psnr"] < 60
    capsys.readouterr()
    assert main(["model", "info", "--method", method, "--profile", "smoke", "--json"]) == 0
    components = json.loads(capsys.readouterr().out)["components"]
    assert components["main.hash_tables"] > 0 and components["background"] > 0


def test_a_table_too_large_for_the_machine_is_named_by_the_memory_check():
    cfg = TrainConfig(
        method="ngp", profile="paper", overrides={"ngp.levels": 32, "ngp.log2_table_size": 24}
    )
    estimate = estimate_peak_bytes(cfg.method, cfg.resolved_profile(), 100)
    # the 14 finest of 32 levels fill 2^24 entries x 2 features, at 16 bytes a parameter (weights,
    # gradients, Adam's moments): over 7 GiB
    full = sum((n + 1) ** 3 >= 2**24 for n in level_resolutions(32, 16, 2048))
    assert full == 14 and estimate["parts"]["parameters"] > full * 2**24 * 2 * 16
    assert "ngp.log2_table_size" in describe(estimate)


def test_a_killed_ngp_leco_run_resumes_from_its_checkpoint(tiny_scene, tmp_path):
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "cli", "train", "--scene", str(tiny_scene.root)]
    cmd += ["--method", "ngp-leco", "--profile", "smoke", "--out", str(out), "--backend", "local"]
    cmd += ["--checkpoint-every", "10", "--set", "main_steps=300"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    main_rows = lambda: [r for r in read_metrics(out / "metrics.jsonl") if r["phase"] == "main"]
    # steps count on from phase 1's 20 (the smoke profile's): the main phase's are 21 to 320
    while not (out / "metrics.jsonl").exists() or not main_rows() or main_rows()[-1]["step"] < 50:
        assert time.monotonic() < deadline and proc.poll() is None, "the run should still be going"
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert main_rows()[-1]["step"] < 320
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    steps = [r["step"] for r in main_rows()]
    assert steps == list(range(30, 321, 10))  # nothing missing, nothing twice
    assert json.loads((out / "summary.json").read_text())["steps"]["phases"]["main"] == 300


@pytest.mark.slow
@ON_POSTGRESQL  # one database: the service's own tests run both
def test_ngp_leco_trains_through_the_api_and_a_dispatcher(service_settings):
    from service.dispatcher import Dispatcher

    # a job's slot of 24,000 MB, whatever this machine's RAM
    settings = service_settings.model_copy(update={"backend": "local", "slot_memory_mb": 24_000})
    with api_client(settings) as api:
        listed = {m["name"]: m for m in api.get("/v1/methods").json()["items"]}
        assert listed["ngp-leco"]["phases"] == ["occupancy", "main"]
        scene = api.post("/v1/scenes/synthetic", json={"preset": "tiny", "seed": 0}).json()
        while scene["state"] == "generating":
            time.sleep(0.2)
            scene = api.get(f"/v1/scenes/{scene['id']}").json()
        body = {"scene": scene["id"], "method": "ngp-leco", "profile": "smoke"}
        # 2^24 rows of 8 features at 16 levels: about 30 GiB with Adam's state and a step's samples
        too_big = {
            **body,
            "profile": "paper",
            "overrides": {"ngp.log2_table_size": 24, "ngp.features": 8},
        }
        refused = api.post("/v1/jobs", json=too_big)
        assert refused.status_code == 422 and "ngp.log2_table_size" in refused.text
        job = api.post("/v1/jobs", json={**body, "overrides": {"main_steps": 10}})
        assert job.status_code == 201, job.text
        dispatcher = Dispatcher(settings, poll_s=0.2)
        threading.Thread(target=dispatcher.run_forever, daemon=True).start()
        try:
            done = lambda j: j["state"] in ("succeeded", "failed")
            state = wait_for(api, job.json()["id"], done, timeout=180)
        finally:
            dispatcher.stop(wait=True)
        assert state["state"] == "succeeded", state["error"]
        assert state["latest_metrics"]["main"]["loss"] > 0


def test_ngp_grid_cascades_read_the_background_beyond_the_box():
    import torch

    profile = TrainConfig(method="ngp", profile="smoke").resolved_profile()
    method = get_method("ngp")(profile)
    models = method.build(3, torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    assert method.grid.levels == profile.ngp.grid.levels == 2
    r = profile.ngp.grid.resolution
    assert method.components(3)["grid_cells"] == 2 * r**3 == method.grid.num_cells
    x = torch.tensor([[0.2, 0.0, 0.0], [1.5, 0.0, 0.0]])
    zeros = torch.zeros(1, dtype=torch.long)
    with torch.no_grad():
        sigma = method.density(models, x)
        inside = models.field(x[:1], torch.zeros(1, 3), zeros).sigma
        outside = models.background(x[1:], torch.zeros(1, 3), zeros)[0]
    assert torch.allclose(sigma, torch.cat([inside, outside]).float())
    assert get_method("grid")(profile).grid_config.levels == 1  # S+Grid: nerfacc's one level


def test_an_ngp_run_renders_a_video_and_exports_its_grid_and_points(tiny_scene, tmp_path, capsys):
    from workers.render.video import probe

    run = tmp_path / "run"
    args = ["train", "--scene", str(tiny_scene.root), "--method", "ngp", "--profile", "smoke"]
    assert main(args + ["--out", str(run), "--backend", "local", "--set", "main_steps=8"]) == 0
    video = tmp_path / "orbit.mp4"
    render = ["render", "--run", str(run), "--frames", "2", "--size", "32x24", "--fps", "4"]
    assert main(render + ["--out", str(video)]) == 0
    assert probe(video)["frames"] == 2 and probe(video)["width"] == 32
    for what, name in (("occupancy", "occupancy.ply"), ("pointcloud", "pointcloud.ply")):
        out = tmp_path / what
        export = ["export", what, "--run", str(run), "--out", str(out), "--stride", "4"]
        assert main(export + ["--min-opacity", "0", "--resolution", "16"]) == 0
        assert (out / name).stat().st_size > 100
    capsys.readouterr()


def test_ngp_images_stop_each_ray_once_it_is_opaque():
    """Validation and renders march a ray only until its transmittance is below the grid's
    early_stop_eps (Instant-NGP's renders); training's render_main keeps every sample."""
    import torch
    from torch import nn

    from model.fields.output import FieldOutput
    from model.scenes.rays import RayBatch

    class Dense(nn.Module):  # the real field, made opaque: every ray stops early
        def __init__(self, field):
            super().__init__()
            self.field = field

        def forward(self, xyz, dirs, image):
            out = self.field(xyz, dirs, image)
            return FieldOutput(out.sigma + 50.0, out.rgb, out.gate_probs, out.expert, out.kept)

    torch.manual_seed(0)
    profile = TrainConfig(method="ngp", profile="smoke").resolved_profile()
    assert profile.ngp.grid.early_stop_eps == 1e-4
    method = get_method("ngp")(profile)
    models = method.build(3, torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    models.field = Dense(models.field)
    n = 32
    origins = torch.tensor([[0.0, 0.0, -3.0]]).expand(n, 3)
    directions = nn.functional.normalize(
        torch.randn(n, 3) * 0.1 + torch.tensor([0, 0, 1.0]), dim=-1
    )
    rays = RayBatch(
        origins,
        directions,
        torch.full((n,), 2.0),
        torch.full((n,), 4.0),
        torch.zeros(n, dtype=torch.long),
        torch.zeros(n, 3),
        torch.arange(n),
    )
    with torch.no_grad():
        every = method.render_main(models, rays, None, None)
        image = method.render(models, "main", rays)
    # one block of 16 samples a ray instead of all ~37 the smoke grid marches
    assert len(image.weights) <= 16 * n < 0.5 * len(every.rendered.weights)
    assert (image.rgb - every.rendered.rgb).abs().max() < 1e-3

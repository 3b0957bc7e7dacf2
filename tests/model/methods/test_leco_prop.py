"""LeCO+Prop (model/methods/leco_prop.py): the proposals sample only where O's keep lets them, learn
on that axis, and the method trains wherever the others do (`leco train`, a checkpoint after a
kill, the API on SQLite and PostgreSQL)."""

import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest
import torch

from cli.main import main
from model.estimators.guided import BinOptions, keep_bins
from model.estimators.kept_axis import bounded
from model.methods import family_of, get_method
from model.methods.base import Step
from model.render.noise import Noise
from model.scenes import RaySampler
from tests.helpers import ON_SQLITE, ROOT, api_client, wait_for
from tests.workers.train.test_training import read_metrics
from workers.config import TrainConfig


def started(tiny_scene, **overrides):
    """A leco-prop at the smoke profile, built and in its main phase, and a batch of 64 rays."""
    profile = TrainConfig(
        method="leco-prop", profile="smoke", overrides=overrides
    ).resolved_profile()
    method = get_method("leco-prop")(profile)
    torch.manual_seed(0)
    models = method.build(tiny_scene.num_images, tiny_scene.bounds.aabb)
    method.start_phase(models, "main", True, torch.device("cpu"), lambda _: None)
    rays = RaySampler(tiny_scene.train, tiny_scene.bounds.aabb, 64, 0, 0, 1).next()
    return method, models, rays


def test_both_families_have_a_leco_prop_that_reads_its_own_sections():
    assert "leco-prop" in family_of("leco") and "ngp-leco-prop" in family_of("ngp")
    profile = TrainConfig(method="leco-prop", profile="cpu").resolved_profile()
    leco = TrainConfig(method="leco", profile="cpu").resolved_profile()
    # LeCO's phase 1 and keep/drop, without O's placement head: the proposals place the samples
    assert profile.occupancy == leco.occupancy
    assert not profile.guided.placement and profile.guided.empty_threshold == 0.9
    assert profile.prop.samples == (32, 32) and profile.prop.main_samples == 21
    assert profile.leco_prop.bound == "range"


@pytest.mark.parametrize("bound", ["range", "mask", "level"])
def test_no_main_sample_lies_outside_the_bins_o_lets_the_proposals_use(bound, tiny_scene):
    placement = {"leco_prop.guided.placement": bound == "level"}
    method, models, rays = started(tiny_scene, **{"leco_prop.bound": bound, **placement})
    with torch.no_grad():
        render = method.render_main(models, rays, None, None)  # deterministic: no jitter
        hit = torch.nonzero(rays.far > rays.near)[:, 0]
        sub = rays.subset(hit)
        bins = keep_bins(
            sub.near,
            sub.far,
            sub.origins,
            sub.directions,
            method.query.occupied,
            None,
            BinOptions.of(method.profile.guided),
            method.query.scores,
        )
    allowed = bounded(bins.keep, "mask" if bound == "level" else bound)
    samples = render.samples
    row = torch.searchsorted(hit, samples.ray_index)  # the hit ray each sample belongs to
    t = samples.mids
    edges = bins.edges[row]
    b = (torch.searchsorted(edges.contiguous(), t[:, None].contiguous()) - 1)[:, 0]
    b = b.clamp(0, allowed.shape[1] - 1)
    on_edge = (t == edges.gather(1, b[:, None])[:, 0]) | (
        t == edges.gather(1, b[:, None] + 1)[:, 0]
    )
    positive = samples.deltas > 0  # zero-long intervals hold no weight wherever they are
    assert (allowed[row, b] | on_edge | ~positive).all()
    if bound != "range":  # O drops some bins between kept ones on this untrained O
        assert bool((bounded(bins.keep, "range") & ~bins.keep).any())
    # a ray that misses the box shows its background alone
    missed = rays.far <= rays.near
    assert bool(missed.any()) and float(render.rendered.opacity[missed].abs().max()) == 0.0


def test_a_step_trains_both_proposal_levels_and_o_on_the_bounded_axis(tiny_scene):
    overrides = {"leco_prop.guided.online": True, "leco_prop.guided.online_warmup": 0}
    method, models, rays = started(tiny_scene, **overrides)
    g = torch.Generator().manual_seed(0)
    render, levels, edges = method.draw(models, rays, Noise(g), 0, learn=True)
    kept = render.stats["bounded_length"]
    assert 0.0 < kept <= 1.0
    # the first level spans each ray's axis, [0, its kept length]; every later edge lies on it
    first = levels[0][0]
    assert torch.equal(first[:, 0], torch.zeros(len(edges)))
    length = first[:, -1:]
    assert bool((length > 0).all()) and bool((length <= rays.far.max() - rays.near.min()).all())
    for later in [e for e, _ in levels[1:]] + [edges]:
        assert bool((later >= 0).all()) and bool((later <= length + 1e-6).all())
    loss, parts = method.step(models, Step("main", rays, Noise(g), 0.0, 0, seed=0))
    loss.backward()
    assert parts["interlevel_loss"] >= 0 and parts["occupancy_online_loss"] > 0
    for level in models.proposals:
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in level.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in models.hmoe.gate.parameters())
    assert parts["samples_per_hit_ray"] == method.profile.prop.main_samples


def test_phase_1_can_warm_the_proposals_on_the_hmoes_weights(tiny_scene):
    method, models, rays = started(tiny_scene, **{"leco_prop.prop_in_phase1": True})
    assert models.proposals in method.trained_modules(models, "occupancy")
    g = torch.Generator().manual_seed(0)
    loss, parts = method.step(models, Step("occupancy", rays, Noise(g), 0.0, 0, seed=0))
    loss.backward()
    assert parts["interlevel_loss"] > 0 and "imbalanced_gate_loss" in parts
    for level in models.proposals:
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in level.parameters())
    # off (the default), phase 1 is LeCO's and the proposals wait for the main phase
    method, models, rays = started(tiny_scene)
    assert models.proposals not in method.trained_modules(models, "occupancy")
    loss, parts = method.step(models, Step("occupancy", rays, Noise(g), 0.0, 0, seed=0))
    assert "interlevel_loss" not in parts


def test_explore_sends_a_share_of_the_samples_outside_the_bound(tiny_scene):
    method, models, rays = started(tiny_scene, **{"leco_prop.explore": 0.2})
    render = method.render_main(models, rays, None, None)
    plain = started(tiny_scene)
    bounded_only = plain[0].render_main(plain[1], plain[2], None, None)
    # the axis is longer by a fifth of what the bound left out
    assert render.stats["bounded_length"] > bounded_only.stats["bounded_length"]
    assert render.stats["bounded_length"] <= 1.0


def test_in_the_level_form_os_histogram_is_the_first_level_and_learns_with_the_proposals(
    tiny_scene,
):
    overrides = {"leco_prop.bound": "level", "leco_prop.guided.placement": True}
    method, models, rays = started(tiny_scene, **overrides)
    g = torch.Generator().manual_seed(0)
    render, levels, edges = method.draw(models, rays, Noise(g), 0, learn=True)
    coarse = method.profile.guided.coarse_samples
    # O's coarse bins, then one level per proposal network
    assert [e.shape[1] - 1 for e, _ in levels] == [coarse, *method.profile.prop.samples]
    loss = method.step(models, Step("main", rays, Noise(g), 0.0, 0, seed=0))[0]
    loss.backward()
    head = models.hmoe.gate
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in head.parameters())
    with pytest.raises(ValueError, match="leco_prop.bound=level .* set leco_prop.guided.placement"):
        TrainConfig(
            method="leco-prop", profile="smoke", overrides={"leco_prop.bound": "level"}
        ).resolved_profile()


def test_a_ray_with_nothing_kept_renders_its_background_without_nans(tiny_scene):
    method, models, rays = started(tiny_scene, **{"leco_prop.guided.fallback": False})
    method.query.occupied = lambda points: torch.zeros(len(points), dtype=torch.bool)
    g = torch.Generator().manual_seed(0)
    loss, parts = method.step(models, Step("main", rays, Noise(g), 0.0, 0, seed=0))
    loss.backward()
    assert torch.isfinite(loss) and parts["bounded_length"] == 0.0
    render = method.render_main(models, rays, None, None)
    assert float(render.rendered.opacity.abs().max()) == 0.0


def test_the_control_arm_asks_o_nothing_and_samples_the_whole_segment(tiny_scene):
    method, models, rays = started(tiny_scene, **{"leco_prop.bound": "off"})
    method.query.occupied = None  # asking O would fail
    render = method.render_main(models, rays, None, None)
    hit = rays.far > rays.near
    first = render.samples.starts.reshape(int(hit.sum()), -1)[:, 0]
    assert torch.allclose(first, rays.near[hit], atol=1e-5)
    assert "bounded_length" not in render.stats


@pytest.mark.parametrize("method", ["leco-prop", "ngp-leco-prop"])
def test_each_leco_prop_trains_renders_and_exports_through_the_cli(
    method, tiny_scene, tmp_path, capsys
):
    out = tmp_path / "run"
    args = ["train", "--scene", str(tiny_scene.root), "--method", method, "--profile", "smoke"]
    args += ["--out", str(out), "--backend", "local", "--set", "main_steps=12"]
    assert main(args) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["method"] == method and summary["steps"]["phases"]["main"] == 12
    assert 5 < summary["val"]["psnr"] < 60
    assert summary["occupancy"]["params"] > 0  # O is saved and scored
    capsys.readouterr()
    assert main(["model", "info", "--method", method, "--profile", "smoke", "--json"]) == 0
    components = json.loads(capsys.readouterr().out)["components"]
    assert components["proposal_networks"] > 0 and components["occupancy_network"] > 0
    # a finished run renders a video along a camera path and exports O's occupancy and its points
    from workers.render.video import probe

    video = tmp_path / "orbit.mp4"
    render = ["render", "--run", str(out), "--frames", "2", "--size", "32x24", "--fps", "4"]
    assert main(render + ["--out", str(video)]) == 0
    assert probe(video)["frames"] == 2 and probe(video)["width"] == 32
    for what, name in (("occupancy", "occupancy.ply"), ("pointcloud", "pointcloud.ply")):
        folder = tmp_path / what
        export = ["export", what, "--run", str(out), "--out", str(folder), "--stride", "4"]
        assert main(export + ["--min-opacity", "0", "--resolution", "16"]) == 0
        assert (folder / name).stat().st_size > 100
    capsys.readouterr()


def test_a_killed_leco_prop_run_resumes_from_its_checkpoint(tiny_scene, tmp_path):
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "cli", "train", "--scene", str(tiny_scene.root)]
    cmd += ["--method", "leco-prop", "--profile", "smoke", "--out", str(out), "--backend", "local"]
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
@ON_SQLITE  # one database: the service's own tests run both
def test_leco_prop_trains_through_the_api_and_a_dispatcher(service_settings):
    from service.dispatcher import Dispatcher

    settings = service_settings.model_copy(update={"backend": "local"})
    with api_client(settings) as api:
        listed = {m["name"]: m for m in api.get("/v1/methods").json()["items"]}
        assert listed["leco-prop"]["phases"] == ["occupancy", "main"]
        scene = api.post("/v1/scenes/synthetic", json={"preset": "tiny", "seed": 0}).json()
        while scene["state"] == "generating":
            time.sleep(0.2)
            scene = api.get(f"/v1/scenes/{scene['id']}").json()
        body = {"scene": scene["id"], "method": "leco-prop", "profile": "smoke"}
        wrong = api.post("/v1/jobs", json={**body, "overrides": {"leco_prop.bound": "box"}})
        assert wrong.status_code == 422 and "leco_prop.bound" in wrong.text
        overrides = {"main_steps": 10, "leco_prop.bound": "mask"}
        job = api.post("/v1/jobs", json={**body, "overrides": overrides})
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

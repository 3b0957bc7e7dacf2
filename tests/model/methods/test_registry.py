"""Methods have one home: a method is a class behind model/methods/base.py plus one registry line
(its spec). A toy method registered here trains through `leco train` and through the API without any
other module knowing its name; the loop, evaluation, bench and API compare no method names."""

import ast
import json
import threading
import time

import pytest
import torch

from cli.main import main
from model.methods import METHODS, Method, MethodSpec, PhaseMemory, get_method, register
from model.methods.base import method_state
from model.methods.costs import main_phase
from model.methods.leco.phase1 import render_background
from model.methods.main_phase import MainRender, render_batched
from model.render.samples import stratified_edges
from tests.helpers import ON_SQLITE, ROOT, api_client
from workers.config import TrainConfig


class UniformSamples(Method):
    """The toy: the main network on 6 stratified samples per ray, nothing else."""

    def render_main(self, models, rays, noise, phase_step) -> MainRender:
        behind = render_background(
            models.background, rays, self.profile.background.samples, noise
        ).rgb
        rendered, out = render_batched(
            models.field, rays, stratified_edges(rays.near, rays.far, 6, noise), behind
        )
        return MainRender(rendered, out, 6.0, None)


def uniform_memory(profile, num_images) -> dict[str, PhaseMemory]:
    return {"main": main_phase(profile, num_images, samples_per_ray=6)}


TOY = MethodSpec("toy-uniform", "S+Uniform (toy)", UniformSamples, uniform_memory)


@pytest.fixture
def toy():
    register(TOY)
    yield TOY
    METHODS.pop(TOY.name)


def test_registry_lists_every_method_once_and_refuses_a_second_owner_of_a_name():
    assert list(METHODS) == [
        "leco",
        "switch",
        "grid",
        "prop",
        "leco-prop",
        "ngp",
        "ngp-leco",
        "ngp-prop",
        "ngp-leco-prop",
    ]
    roles = [get_method(n).role for n in METHODS]
    # each family has its pair: Switch-NeRF's, then the hash grids' (Table 6)
    assert (
        roles == ["ours", "reference"] + ["baseline"] * 3 + ["reference", "ours"] + ["baseline"] * 2
    )

    with pytest.raises(ValueError, match="'grid' is already registered"):
        register(MethodSpec("grid", "Impostor", UniformSamples, uniform_memory))
    with pytest.raises(
        ValueError,
        match="unknown method 'nope': choose one of leco, switch, grid, prop, leco-prop, ngp",
    ):
        TrainConfig(method="nope")


def test_a_method_reads_a_shared_section_from_a_section_of_its_own():
    # a toy that samples as LeCO's sampler says, with ngp-leco's section as its own
    spec = MethodSpec(
        "toy-own",
        "S+Own (toy)",
        UniformSamples,
        uniform_memory,
        sections=(("guided", "ngp_leco.guided"),),
    )
    register(spec)
    try:
        resolve = lambda method, **o: TrainConfig(method=method, profile="cpu", overrides=o)
        assert resolve("toy-own").resolved_profile().guided.coarse_samples == 64
        own = resolve("toy-own", **{"ngp_leco.guided.coarse_samples": 40}).resolved_profile()
        assert own.guided.coarse_samples == 40
        # every other method keeps the profile's value
        assert resolve("switch").resolved_profile().guided.coarse_samples == 16
        with pytest.raises(ValueError, match="set 'ngp_leco.guided.split' instead"):
            resolve("toy-own", **{"guided.split": 2})
    finally:
        METHODS.pop(spec.name)


def test_checkpoints_from_before_the_registry_keep_their_grid_state():
    old = {
        "models": {},
        "grid": {"values": torch.ones(8), "binary": torch.ones(8, dtype=torch.bool), "queries": 3},
    }
    assert method_state(old) is old["grid"]
    assert method_state({"models": {}, "method": {"since_update": 2}, "grid": None}) == {
        "since_update": 2
    }


@pytest.mark.slow
def test_a_registered_toy_method_trains_through_leco_train(toy, tiny_scene, tmp_path, capsys):
    out = tmp_path / "run"
    assert (
        main(
            [
                "train",
                "--scene",
                str(tiny_scene.root),
                "--method",
                toy.name,
                "--profile",
                "smoke",
                "--out",
                str(out),
                "--backend",
                "local",
                "--set",
                "main_steps=8",
            ]
        )
        == 0
    )
    summary = json.loads((out / "summary.json").read_text())
    assert summary["method"] == toy.name and summary["steps"]["phases"] == {"main": 8}
    assert summary["samples_per_ray"] == 6.0 and summary["val"]["psnr"] > 5
    capsys.readouterr()
    assert main(["model", "info", "--method", toy.name, "--profile", "smoke", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["method"] == toy.name and info["components"]["background"] > 0


@pytest.mark.slow
@ON_SQLITE  # one database: the service's own tests run both
def test_a_registered_toy_method_trains_through_the_api(toy, service_settings):
    from service.dispatcher import Dispatcher

    # registered in this process only: trained in the dispatcher's thread, not a child process
    settings = service_settings.model_copy(update={"backend": "local", "local_in_child": False})
    with api_client(settings) as api:
        listed = {m["name"]: m for m in api.get("/v1/methods").json()["items"]}
        assert listed[toy.name] == {
            "name": toy.name,
            "label": toy.label,
            "role": "baseline",
            "phases": ["main"],
            "has_occupancy": False,
        }
        scene = api.post("/v1/scenes/synthetic", json={"preset": "tiny", "seed": 0}).json()
        while scene["state"] == "generating":
            time.sleep(0.2)
            scene = api.get(f"/v1/scenes/{scene['id']}").json()
        body = {
            "scene": scene["id"],
            "method": toy.name,
            "profile": "smoke",
            "overrides": {"main_steps": 6},
        }
        job = api.post("/v1/jobs", json=body)
        assert job.status_code == 201, job.text
        dispatcher = Dispatcher(settings, poll_s=0.2)
        threading.Thread(target=dispatcher.run_forever, daemon=True).start()
        try:
            deadline = time.monotonic() + 180
            while (state := api.get(f"/v1/jobs/{job.json()['id']}").json())["state"] not in (
                "succeeded",
                "failed",
            ):
                assert time.monotonic() < deadline, state
                time.sleep(0.3)
        finally:
            dispatcher.stop(wait=True)
        assert state["state"] == "succeeded", state["error"]
        assert api.get("/v1/jobs", params={"method": toy.name}).json()["total"] == 1
        refused = api.get("/v1/jobs", params={"method": "nope"})
        assert (
            refused.status_code == 422
            and "choose one of" in refused.text
            and toy.name in refused.text
        )


# Modules that run, evaluate, serve and report every method: none may compare a method's name.
GENERIC = [
    *[str(p.relative_to(ROOT)) for p in sorted((ROOT / "workers" / "train").glob("*.py"))],
    "workers/appearance.py",
    "workers/models.py",
    "workers/config.py",
    "service/execute.py",
    "service/dispatcher.py",
    *[str(p.relative_to(ROOT)) for p in (ROOT / "service" / "api").glob("*.py")],
    "bench/analysis.py",
    "bench/report.py",
    "bench/runner.py",
    "bench/reference.py",
    "model/memory_estimate.py",
    "model/model_info.py",
]


@pytest.mark.parametrize("path", GENERIC)
def test_generic_modules_name_no_method(path):
    tree = ast.parse((ROOT / path).read_text())
    named = [
        (node.lineno, node.value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Constant) and node.value in METHODS
    ]
    assert named == [], f"{path} names methods: {named}"

"""The job setting `compile` (workers/train/compiled.py): the networks compiled in place train the
same steps as eager ones, keep their names, and a machine that cannot compile says so first."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from model.methods.parts import read_parts
from model.profiles import MAX_STEPS
from tests.helpers import ROOT
from workers import toolchain
from workers.config import TrainConfig
from workers.toolchain import cpp_compiler
from workers.train.compiled import COMPILED, CompileUnavailable, check_can_compile, compile_modules
from workers.train.loop import RankRun
from workers.train.session import LocalSession


def three_steps(scene, run_dir, method: str, compile: bool) -> tuple[list[dict], RankRun]:
    torch._dynamo.reset()
    cfg = TrainConfig(
        method=method,
        profile="smoke",
        metrics_every=MAX_STEPS,
        checkpoint_every=MAX_STEPS,
        overrides={"rays_per_device": 64},
        compile=compile,
    )
    run = RankRun(cfg, scene.root, run_dir, LocalSession(run_dir / "s"), torch.device("cpu"))
    run.start_phase("main", fresh=True)
    objects = run.current_phase()
    parts = [read_parts(run.train_step("main", objects)) for _ in range(3)]
    return parts, run


def eager_and_compiled(method: str, scene_root: Path, out: Path) -> dict:
    """Three steps eager and three compiled from the same seed: their parts, whether every network
    the phase compiles was compiled, and the parameters that differ after three Adam steps (beyond
    float32 rounding of a fused order)."""
    from model.scenes import load_scene

    scene = load_scene(scene_root)
    eager, eager_run = three_steps(scene, out / "eager", method, compile=False)
    fused, fused_run = three_steps(scene, out / "compiled", method, compile=True)
    torch._dynamo.reset()
    eager_params = dict(eager_run.models.named_parameters())
    return {
        "eager": eager,
        "compiled": fused,
        "all_compiled": all(
            getattr(m, COMPILED, False)
            for m in fused_run.method.compiled_modules(fused_run.models, "main")
        ),
        "same_names": list(eager_run.models.state_dict()) == list(fused_run.models.state_dict()),
        "params_apart": [
            name
            for name, p in fused_run.models.named_parameters()
            if not torch.allclose(p, eager_params[name], rtol=1e-4, atol=1e-6)
        ],
    }


@pytest.mark.slow
@pytest.mark.skipif(cpp_compiler() is None, reason="inductor needs a C++ compiler (g++) here")
@pytest.mark.parametrize("method", ["ngp-prop", "prop"])
def test_a_compiled_run_trains_the_same_three_steps_as_an_eager_one(tiny_scene, tmp_path, method):
    # prop's Switch-NeRF reads its experts' group sizes inside the field (a symbolic size when
    # compiled); ngp-prop's hash field is all gathers and arithmetic, fused by inductor. Both in a
    # process of their own, as a training worker compiles: inductor's kernels run outside whatever
    # the rest of the suite left in pytest's process, and a kernel that kills its process fails
    # this test with what it printed instead of ending the suite.
    done = subprocess.run(
        [sys.executable, "-m", __name__, method, str(tiny_scene.root), str(tmp_path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, f"exit {done.returncode}:\n{done.stderr[-3000:]}"
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["all_compiled"] and result["same_names"]
    for a, b in zip(result["eager"], result["compiled"], strict=True):
        assert b["loss"] == pytest.approx(a["loss"], rel=1e-4)
        assert b["rendering_loss"] == pytest.approx(a["rendering_loss"], rel=1e-4)
        assert b["samples_per_ray"] == a["samples_per_ray"]
    # the parameters after three Adam steps: the same to float32 rounding of a fused order
    assert result["params_apart"] == []


def test_compile_modules_compiles_each_module_once_and_keeps_its_names():
    net = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.ReLU())
    names = list(net.state_dict())
    assert compile_modules([net, net]) == 1
    assert compile_modules([net]) == 0
    assert list(net.state_dict()) == names
    torch._dynamo.reset()


def test_the_modules_a_phase_compiles_are_the_networks_it_trains_each_proposal_on_its_own():
    from model.methods import get_method
    from model.profiles import PROFILES

    method = get_method("prop")(PROFILES["smoke"])
    models = method.build(4, torch.tensor([[-1.0, -1, -1], [1, 1, 1]]))
    modules = method.compiled_modules(models, "main")
    assert modules[:2] == [models.field, models.background]
    assert modules[2:] == list(models.proposals) and len(modules) == 2 + len(models.proposals)


def test_a_cpu_without_a_cpp_compiler_fails_before_training_naming_what_is_missing(monkeypatch):
    monkeypatch.setattr(toolchain.shutil, "which", lambda name: None)
    with pytest.raises(CompileUnavailable, match="needs a C\\+\\+ compiler.*compile=false"):
        check_can_compile(torch.device("cpu"))
    check_can_compile(torch.device("cuda"))  # a GPU's kernels are Triton's: nothing to check here


@pytest.mark.parametrize("static_shapes", [True, False])
@pytest.mark.parametrize("perturb", [True, False])
def test_an_ngp_prop_step_with_static_shapes_traces_as_one_graph(
    tiny_scene, static_shapes, perturb
):
    """Capture-safe: with `prop.static_shapes` dynamo traces NGP+Prop's whole step (sampler,
    field, background, losses, and its random draws, which come from the default generator) as one
    graph; picking out the hits breaks it at the nonzero and nowhere else."""
    from model.methods import get_method
    from model.methods.base import Step
    from model.render.noise import Noise
    from model.scenes import RaySampler

    profile = TrainConfig(
        method="ngp-prop", profile="smoke", overrides={"prop.static_shapes": static_shapes}
    ).resolved_profile()
    method = get_method("ngp-prop")(profile)
    torch.manual_seed(0)
    models = method.build(tiny_scene.num_images, tiny_scene.bounds.aabb)
    rays = RaySampler(tiny_scene.train, tiny_scene.bounds.aabb, 64, 0, 0, 1).next()
    step = Step("main", rays, Noise() if perturb else None, 0.5, 0, seed=0)
    torch._dynamo.reset()
    try:
        explained = torch._dynamo.explain(method.step)(models, step)
    finally:
        torch._dynamo.reset()
    reasons = [r.reason for r in explained.break_reasons]
    if static_shapes:
        assert (explained.graph_count, explained.graph_break_count) == (1, 0), reasons
    else:
        assert explained.graph_break_count > 0
        assert all("nonzero" in reason for reason in reasons), reasons


def test_leco_compiles_its_main_networks_and_not_the_hmoe_of_phase_1():
    from model.methods import get_method
    from model.profiles import PROFILES

    method = get_method("leco")(PROFILES["smoke"])
    models = method.build(4, torch.tensor([[-1.0, -1, -1], [1, 1, 1]]))
    assert method.compiled_modules(models, "occupancy") == []
    assert method.compiled_modules(models, "main") == [models.field, models.background]


if __name__ == "__main__":  # the compared run, in its own process: METHOD SCENE_DIR OUT_DIR
    print(json.dumps(eager_and_compiled(sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3]))))

"""`leco bench-step`: the op, sync and graph-break counters on toy functions whose counts are known,
and one real step of a method on the tiny scene."""

import json

import pytest
import torch
from torch.profiler import record_function

from bench.step_profile import count_steps, graph_breaks, profile_steps
from cli.main import main
from model.methods.stages import HOST_DRAW, STAGES, host_read, stage


def counted(fn, steps: int = 2):
    return count_steps(profile_steps(fn, steps))


def test_each_host_sync_counts_once_and_host_side_reads_do_not():
    x = torch.randn(100)
    mask = x > 0
    repeats = torch.randint(0, 3, (100,))

    def syncing():
        x.sum().item()  # 1
        float(x.mean())  # 1
        bool(mask.any())  # 1
        torch.nonzero(mask)  # 1
        x[mask]  # 1: boolean indexing runs a nonzero
        x.masked_select(mask)  # 1 (on the CPU its own scalar read)
        torch.unique(repeats)  # 1
        x.repeat_interleave(repeats)  # 2: its total and its check
        x.repeat_interleave(repeats, output_size=int(repeats.sum()))  # 1: the int(), not the op
        x.repeat_interleave(3)  # 0
        x.clone()[mask] = 0.0  # 0: a host scalar filled in
        x[:3].tolist()  # 0: no operator runs on the CPU, so the code reads through host_read
        host_read(x[:3])  # 1
        with record_function(HOST_DRAW):  # 0: a prefetched batch, drawn on the host on CUDA too
            torch.nonzero(mask)
            x.sum().item()
        with stage("ray_batch"):  # made on the run's device: its waits are the step's
            torch.nonzero(mask)  # 1
            x.to("cpu")  # 0: no copy

    steps = counted(syncing)
    assert [s.syncs for s in steps] == [12, 12]
    assert steps[0].syncs_by_op == {
        "aten::_local_scalar_dense": 6,
        "aten::nonzero": 3,
        "aten::masked_select": 1,
        "aten::_unique2": 1,
        "sync::host_read": 1,
    }
    assert steps[0].stage_syncs == {"other": 11, "ray_batch": 1}


def test_device_ops_count_the_calls_that_reach_a_kernel():
    x, w = torch.randn(8, 4), torch.randn(3, 4)

    def five_ops():
        y = torch.exp(x + 1.0) * 2.0  # 3
        y.view(-1).unsqueeze(0)[:, :3].t()  # views: 0
        torch.empty(5)  # an allocation: 0
        y.to(torch.float32).contiguous()  # no-ops: 0
        with stage("field"):
            torch.nn.functional.linear(y, w)  # 1: linear is its addmm
            y.sum()  # 1: on the CPU, the fill of its output

    steps = counted(five_ops)
    assert [s.ops for s in steps] == [5, 5]
    assert steps[0].stage_ops == {"other": 3, "field": 2}
    assert steps[0].aten_calls > 5  # views, allocations and the composites' calls too
    assert steps[0].syncs == 0


def test_stage_shares_take_the_innermost_label_and_sum_to_the_step():
    def nested():
        with stage("sampler"):
            torch.randn(1000).exp()
            with stage("field"):
                torch.randn(1000).exp()

    [counts] = counted(nested, steps=1)
    assert set(counts.stage_seconds) == {"sampler", "field", "other"}
    assert all(seconds >= 0 for seconds in counts.stage_seconds.values())
    assert sum(counts.stage_seconds.values()) == pytest.approx(counts.seconds)
    assert counts.stage_ops == {"sampler": 2, "field": 2}


def test_graph_breaks_of_a_function_with_one_break_and_of_a_clean_one():
    x = torch.randn(4)

    def breaking(x):
        y = x * 2
        return y + y.sum().item()

    broken = graph_breaks(breaking, x)
    assert (broken["graphs"], broken["graph_breaks"]) == (2, 1)
    assert "item()" in broken["break_reasons"][0]
    assert graph_breaks(lambda x: torch.exp(x * 2 + 1), x) == {
        "graphs": 1,
        "graph_breaks": 0,
        "break_reasons": [],
    }


def test_bench_step_measures_a_real_step(tiny_scene, capsys):
    words = ["bench-step", "--method", "prop", "--profile", "smoke", "--rays", "64"]
    words += ["--steps", "2", "--warmup", "1", "--scene", str(tiny_scene.root), "--json"]
    assert main(words) == 0
    row = json.loads(capsys.readouterr().out)
    assert set(row) == {
        "method",
        "profile",
        "phase",
        "device",
        "rays",
        "steps",
        "warmup",
        "at_step",
        "threads",
        "scene",
        "overrides",
        "compiled",
        "warmup_s",
        "step_ms",
        "rays_per_s",
        "ops_per_step",
        "ops_each_step",
        "aten_calls_per_step",
        "host_syncs_per_step",
        "host_syncs_each_step",
        "host_syncs_by_op",
        "kernels_per_step",
        "cuda_syncs_per_step",
        "stages",
        "compile",
    }
    assert (row["method"], row["phase"], row["device"], row["rays"]) == ("prop", "main", "cpu", 64)
    assert 0 < row["step_ms"]["min"] <= row["step_ms"]["median"] <= row["step_ms"]["max"]
    assert row["rays_per_s"] > 0 and len(row["ops_each_step"]) == 2
    assert row["aten_calls_per_step"] > row["ops_per_step"] > 100
    # the batch is made on the run's device and copies nothing; the losses, the guard and the
    # optimizer read nothing (the sampler's own reads remain)
    assert "aten::to" not in row["host_syncs_by_op"]
    for name in ("ray_batch", "losses", "backward", "optimizer", "other"):
        assert row["stages"][name]["syncs"] == 0, name
    assert (row["kernels_per_step"], row["cuda_syncs_per_step"], row["compile"]) == (None,) * 3
    stages = row["stages"]
    assert list(stages) == [*STAGES, "other"]
    assert sum(s["share"] for s in stages.values()) == pytest.approx(1.0, abs=1e-3)
    for name in ("ray_batch", "sampler", "field", "background", "losses", "backward", "optimizer"):
        assert stages[name]["share"] > 0 and stages[name]["ops"] > 0, name
    assert sum(s["ops"] for s in stages.values()) == pytest.approx(row["ops_per_step"], abs=1)


def test_the_expert_dispatch_waits_on_the_device_once_a_forward():
    """Switch-NeRF's dispatch reads its group sizes once (a gather per expert waited once per
    expert); the HMoE reads the empty expert's share once more."""
    from model.fields import HMoE, SwitchNeRF

    torch.manual_seed(0)
    xyz, dirs = torch.rand(500, 3), torch.nn.functional.normalize(torch.randn(500, 3), dim=-1)
    image = torch.zeros(500, dtype=torch.long)
    switch = SwitchNeRF(num_images=1, width=32, num_experts=8, expert_layers=2)
    hmoe = HMoE(1, width=32, num_scene_experts=8, expert_layers=2)
    for model, syncs in ((switch, 1), (hmoe, 2)):
        out = model(xyz, dirs, image)
        assert len(set(out.expert.tolist())) > 2  # several experts take points
        steps = counted(lambda m=model: m(xyz, dirs, image))
        assert [s.syncs for s in steps] == [syncs, syncs], type(model).__name__

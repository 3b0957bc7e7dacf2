"""`leco bench-step`: one method's training step in isolation, as training runs it.

The run is built by the training loop's own `RankRun` (workers/train/loop.py) for one rank in a
throwaway run folder: the scene, the networks, the method, the ray sampler and the phase's
optimizer. The phase measured (`--phase`, default: the method's main phase) is entered fresh, as a
run enters it (`start_phase(phase, fresh=True)`; LeCO's main phase then starts from an untrained
phase 1). Every step is `RankRun.train_step`, and none is a logging step (`metrics_every` is set
past the run, so no step measures its saved tensors). After `--warmup` steps, `--steps` steps are
timed without the profiler, then as many again are profiled with torch.profiler (CPU activity; CUDA
too with `--gpu`), each inside a `bench::step` label. What it reports, per step:

- **step time**: the wall clock of `train_step` (with `--gpu`, up to a `torch.cuda.synchronize()`
  after it), median, min and max of the timed steps; **rays/s**: the rays of a step over the median.
- **device ops**: calls of `aten::` operators that reach a kernel. A call counts when it does data
  work (its name is not one of METADATA: views, aliases, allocations, no-op conversions and scalar
  reads) and no call of such an operator runs beneath it (it delegates none of its work to another
  aten operator). A composite such as `aten::linear` counts as its `aten::addmm`; `aten::sum`, which
  fills its output first on the CPU, as its `aten::fill_`. The median over the profiled steps. The
  ray batch's ops count too: a GPU run makes its batch on the device (its stage row shows them).
  **aten calls**: every `aten::` event, nested ones included (the dispatcher's work). With
  `--gpu` also **kernels**: kernel launches (the CUDA runtime's `*LaunchKernel*` calls).
- **host syncs**: calls that make the host wait for the device on CUDA, each counted once (one
  beneath another is the same wait). Candidates (SYNC_OPS), each its own profiler event on the
  CPU too: `aten::_local_scalar_dense` (`item()`, `float()`, `int()`, `bool()` of a tensor,
  including the two inside `repeat_interleave` with a tensor of repeats and no `output_size`: its
  total and its check that no repeat is negative; `masked_select` on the CPU), `aten::nonzero`
  (also beneath `torch.where(mask)`, `argwhere`, boolean-mask indexing `x[mask]` and
  `x[mask] = values`), `aten::masked_select`, the `unique` operators, `aten::equal`, and the
  `sync::host_read` label (model/methods/stages.py `host_read`: a `tolist()`, which runs no aten
  operator on the CPU, so the code reads through it where it must read a tensor). On the
  CPU, so that the count is what CUDA would wait on: a candidate beneath host-side work of a CUDA
  run does not count (`Optimizer.step#...`, whose step counters torch.optim keeps on the host;
  `aten::_index_put_impl_`, whose `x[mask] = 0.0` fills with a host scalar; a `host::` label, the
  prefetching thread's drawing of a batch too large to keep on a GPU). The ray batch is made on
  the run's device (workers/train/ray_batches.py): on a GPU from the colours, cameras and order it
  keeps there, so its ops and any wait among them count as the step's. Still counted on the CPU,
  though CUDA would not wait: a read of a tensor made on the host (`torch.tensor(x).item()`); not
  seen on the CPU: copies of host tensors to the device (every tensor is on the one device; the
  step makes none). With `--gpu` a candidate, and any
  `aten::copy_`, counts only when a synchronising CUDA runtime call (SYNC_CALLS) runs beneath
  it, and **cuda syncs** counts those runtime calls themselves.
- **stages**: an event belongs to the innermost stage label around it (model/methods/stages.py: the
  loop labels the ray batch, the backward pass and the optimizer step; the methods their sampler,
  main field, background and losses); an event on another thread with no label (CUDA's autograd
  threads) belongs to `backward` when it runs beneath `autograd::engine`, else to `other`. A
  stage's share is the host time inside its labels, less the stages nested in them, over the
  steps' time; `other` is the rest (compositing, the non-finite guard, the learning rate), so the
  shares sum to 1. With `--gpu` the host runs ahead of the device: a stage's time includes the
  waits at its syncs.
- **compiled** (`--compile`): the run is the job setting `compile` (workers/train/compiled.py:
  the networks each phase calls, compiled in place by inductor). The warm-up steps compile
  (`warmup_s` is their time: give enough of them for a packed method's second, dynamic-shape
  compile); the timed and profiled steps run compiled. Each kernel inductor made for the CPU is a
  profiler event (`cpp_fused_*`, with inductor's kernel profiling on) and counts as one device op;
  the aten calls its code still makes (matrix products, gathers) count as before.
- **graph breaks** (`--compile`): `torch._dynamo.explain` on the method's step (`Method.step` on a
  drawn ray batch: sampler, field, background, losses; not the ray batch, not backward), after the
  timed steps: the number of graphs, of breaks, and the first BREAK_REASONS reasons.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import sys
import tempfile
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import torch
    from torch.autograd.profiler_util import FunctionEvent

    from workers.train.loop import RankRun

ROOT = Path(__file__).resolve().parents[1]  # the checkout: generated scenes live under it
DEFAULT_SCENE = "tiny-0"
STEP_LABEL = "bench::step"
BREAK_REASONS = 5

# aten operators that touch no data: views and aliases, allocations, no-op conversions (a `to` or
# `contiguous` that copies has a `copy_` beneath it), metadata queries, and scalar reads (a host
# sync, counted as one).
METADATA = {
    f"aten::{name}"
    for name in (
        "empty empty_like empty_strided new_empty new_empty_strided resize_ set_ "
        "view view_as _unsafe_view _reshape_alias reshape flatten unflatten as_strided as_strided_ "
        "select slice narrow expand expand_as unsqueeze unsqueeze_ squeeze squeeze_ permute "
        "transpose transpose_ t t_ numpy_T mT movedim diagonal unfold split split_with_sizes chunk "
        "unbind alias detach detach_ lift lift_fresh resolve_conj resolve_neg to type_as "
        "contiguous size stride numel dim is_nonzero is_floating_point is_same_size result_type "
        "requires_grad_ retain_grad item _local_scalar_dense view_as_real view_as_complex"
    ).split()
}
SYNC_OPS = {
    "aten::_local_scalar_dense",
    "aten::nonzero",
    "aten::masked_select",
    "aten::_unique",
    "aten::_unique2",
    "aten::unique_dim",
    "aten::unique_consecutive",
    "aten::unique_dim_consecutive",
    "aten::equal",
}
# On the CPU, what runs beneath these reads host tensors in a CUDA run too: torch.optim keeps its
# step counters on the host, x[mask] = scalar fills with a host scalar, and a prefetched ray batch
# is drawn on the host (model/methods/stages.py HOST_DRAW).
HOST_SIDE = ("Optimizer.step#", "aten::_index_put_impl_", "host::")
SYNC_CALLS = {
    "cudaStreamSynchronize",
    "cudaDeviceSynchronize",
    "cudaEventSynchronize",
    "cudaMemcpy",
}
OTHER = "other"
# The profiler's name of a kernel inductor generated for the CPU (with its kernel profiling on, as
# `--compile` sets it): one fused loop over the data, a device op like an aten call.
FUSED_KERNEL = "cpp_fused_"


# ----- counting a profile
def is_cpu(event: FunctionEvent) -> bool:
    from torch.autograd import DeviceType

    return event.device_type == DeviceType.CPU


def is_work(event: FunctionEvent) -> bool:
    if event.name.startswith(FUSED_KERNEL):  # one of inductor's kernels (--compile)
        return True
    return event.name.startswith("aten::") and event.name not in METADATA


def descendants(event: FunctionEvent) -> Iterable[FunctionEvent]:
    for child in event.cpu_children:
        yield child
        yield from descendants(child)


def ancestors(event: FunctionEvent) -> Iterable[FunctionEvent]:
    parent = event.cpu_parent
    while parent is not None:
        yield parent
        parent = parent.cpu_parent


def is_kernel_launch(event: FunctionEvent) -> bool:
    return event.name.startswith("cu") and "LaunchKernel" in event.name


def reaches_kernel(event: FunctionEvent) -> bool:
    """An aten call doing data work with no such call beneath it (the module's definition)."""
    return is_work(event) and not any(is_work(d) for d in descendants(event))


def sync_candidate(event: FunctionEvent, cuda: bool) -> bool:
    """CUDA: a SYNC_OPS call or a copy with a synchronising runtime call beneath it. CPU: a
    SYNC_OPS call not beneath HOST_SIDE work, or a `host_read` label (a tolist)."""
    from model.methods.stages import HOST_READ

    if cuda:
        return (event.name in SYNC_OPS or event.name == "aten::copy_") and any(
            d.name in SYNC_CALLS for d in descendants(event)
        )
    if event.name == HOST_READ:  # a tolist(), which runs no operator on the CPU
        return True
    host_side = any(a.name.startswith(HOST_SIDE) for a in ancestors(event))
    return event.name in SYNC_OPS and not host_side


def is_host_sync(event: FunctionEvent, cuda: bool) -> bool:
    """A wait of the host for the device (the module's rule), not counted again beneath another."""
    return sync_candidate(event, cuda) and not any(
        sync_candidate(a, cuda) for a in ancestors(event)
    )


def stage_of(event: FunctionEvent) -> str:
    from model.methods.stages import PREFIX

    engine = False
    for above in ancestors(event):
        if above.name.startswith(PREFIX):
            return above.name[len(PREFIX) :]
        engine = engine or above.name.startswith("autograd::engine")
    return "backward" if engine else OTHER


@dataclass
class StepCounts:
    """What one profiled step did (the module's definitions)."""

    seconds: float = 0.0
    ops: int = 0
    aten_calls: int = 0
    syncs: int = 0
    kernels: int = 0
    cuda_syncs: int = 0
    syncs_by_op: Counter = field(default_factory=Counter)
    stage_seconds: defaultdict[str, float] = field(default_factory=lambda: defaultdict(float))
    stage_ops: Counter = field(default_factory=Counter)
    stage_syncs: Counter = field(default_factory=Counter)


def step_windows(events: list[FunctionEvent]) -> list[tuple[float, float]]:
    """(start, end) in µs of each `bench::step` label, in order."""
    marks = [e for e in events if e.name == STEP_LABEL and is_cpu(e)]
    return sorted((e.time_range.start, e.time_range.end) for e in marks)


def step_index(windows: list[tuple[float, float]], at: float) -> int | None:
    for i, (start, end) in enumerate(windows):
        if start <= at <= end:
            return i
    return None


def exclusive_seconds(label: FunctionEvent) -> float:
    """A stage label's time less the stage labels nested in it (the nearest ones)."""
    from model.methods.stages import PREFIX

    nested, pending = 0.0, list(label.cpu_children)
    while pending:
        child = pending.pop()
        if child.name.startswith(PREFIX):
            nested += child.time_range.elapsed_us()
        else:
            pending.extend(child.cpu_children)
    return (label.time_range.elapsed_us() - nested) / 1e6


def count_steps(events: list[FunctionEvent], cuda: bool = False) -> list[StepCounts]:
    """Each profiled step's counts, from the events of `profile_steps`."""
    from model.methods.stages import PREFIX

    windows = step_windows(events)
    steps = [StepCounts(seconds=(end - start) / 1e6) for start, end in windows]
    for event in events:
        if not is_cpu(event):
            continue
        i = step_index(windows, event.time_range.start)
        if i is None or event.name == STEP_LABEL:
            continue
        counts = steps[i]
        if event.name.startswith(PREFIX):
            counts.stage_seconds[event.name[len(PREFIX) :]] += exclusive_seconds(event)
            continue
        if event.name.startswith("aten::"):
            counts.aten_calls += 1
        if reaches_kernel(event):
            counts.ops += 1
            counts.stage_ops[stage_of(event)] += 1
        if is_host_sync(event, cuda):
            counts.syncs += 1
            counts.syncs_by_op[event.name] += 1
            counts.stage_syncs[stage_of(event)] += 1
        counts.kernels += is_kernel_launch(event)
        counts.cuda_syncs += event.name in SYNC_CALLS
    for counts in steps:
        counts.stage_seconds[OTHER] = counts.seconds - sum(counts.stage_seconds.values())
    return steps


def profile_steps(step: Callable[[], Any], steps: int, cuda: bool = False) -> list[FunctionEvent]:
    """`step()` `steps` times under torch.profiler, each inside a `bench::step` label (CUDA:
    synchronised after it, outside the label); the profiler's events."""
    import torch
    from torch.profiler import ProfilerActivity, profile, record_function

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=activities) as prof:
        for _ in range(steps):
            with record_function(STEP_LABEL):
                step()
            if cuda:
                torch.cuda.synchronize()
    return list(prof.events())


# ----- graph breaks
def graph_breaks(fn: Callable[..., Any], *args: Any) -> dict:
    """`fn(*args)` under torch._dynamo.explain: graphs, breaks and the first reasons."""
    import torch._dynamo

    torch._dynamo.reset()
    try:
        explained = torch._dynamo.explain(fn)(*args)
    finally:
        torch._dynamo.reset()
    return {
        "graphs": explained.graph_count,
        "graph_breaks": explained.graph_break_count,
        "break_reasons": [reason_text(r) for r in explained.break_reasons[:BREAK_REASONS]],
    }


def reason_text(reason: Any) -> str:
    """A break's reason in one line: dynamo's first line and its explanation (cut at 200
    characters), then the user frame it broke at."""
    lines = [line.strip() for line in reason.reason.strip().splitlines()]
    why = lines[0] + "".join(
        f": {line.removeprefix('Explanation:').strip()}"
        for line in lines[1:]
        if line.startswith("Explanation:")
    )
    where = reason.user_stack[-1] if reason.user_stack else None
    at = f" ({Path(where.filename).name}:{where.lineno})" if where else ""
    return (why if len(why) <= 200 else why[:199] + "…") + at


# ----- the run
def scene_folder(text: str | None) -> Path:
    """A scene folder, or a benchmark scene's short name (bench/scenes.py; default tiny-0),
    generated under the checkout when absent."""
    from bench.scenes import resolve

    if text and Path(text).is_dir():
        return Path(text).resolve()
    return resolve(text or DEFAULT_SCENE, ROOT, log=lambda line: print(line, file=sys.stderr))


def default_phase(phases: tuple[str, ...]) -> str:
    return "main" if "main" in phases else phases[-1]


def make_run(
    method: str,
    profile: str,
    rays: int,
    scene: Path,
    run_dir: Path,
    device: torch.device,
    compile: bool = False,
    overrides: dict | None = None,
) -> RankRun:
    """The training loop's run of one rank, in `run_dir`; no step of it logs. `compile`: the
    run's networks compiled (workers/train/compiled.py), inductor's CPU kernels each a profiler
    event."""
    from model.profiles import MAX_STEPS
    from workers.config import TrainConfig
    from workers.train.loop import RankRun
    from workers.train.session import LocalSession

    cfg = TrainConfig(
        method=method,
        profile=profile,
        use_gpu=device.type == "cuda",
        metrics_every=MAX_STEPS,
        checkpoint_every=MAX_STEPS,
        overrides={**(overrides or {}), "rays_per_device": rays},
        compile=compile,
    )
    if compile:
        import torch._inductor.config

        torch._inductor.config.cpp.enable_kernel_profile = True
    return RankRun(cfg, scene, run_dir, LocalSession(run_dir / "session"), device)


def enter_phase(run: RankRun, phase: str, at_step: int = 0) -> None:
    """The phase begun fresh, as the loop begins it, its step counter then set to `at_step`: a
    method's schedules read it (LeCO's O learns online from main step 500, its placement anneals
    over 500), so a step past them costs what most of a run's steps cost."""
    if phase not in run.method.phases:
        raise ValueError(
            f"{run.cfg.method} has no phase {phase!r}: one of {', '.join(run.method.phases)}"
        )
    run.progress.update(phase=phase, phase_step=0)
    run.start_phase(phase, fresh=True)
    run.progress.update(phase_step=at_step)


def step_of(run: RankRun, phase: str) -> Callable[[], Any]:
    """One training step of the phase, as `run_phase` takes it."""
    objects = run.current_phase()
    return lambda: run.train_step(phase, objects)


def timed(step: Callable[[], Any], steps: int, cuda: bool = False) -> list[float]:
    """Each step's seconds (CUDA: up to a synchronize after it)."""
    import torch

    seconds = []
    for _ in range(steps):
        started = time.perf_counter()
        step()
        if cuda:
            torch.cuda.synchronize()
        seconds.append(time.perf_counter() - started)
    return seconds


def method_step(run: RankRun, phase: str) -> tuple[Callable[..., Any], tuple]:
    """The method's step and its arguments on the next ray batch, as `RankRun.forward` makes
    them."""
    from model.methods.base import Step
    from model.render.noise import Noise

    rays = run.state.sampler.next()  # on the run's device
    noise = Noise() if run.profile.perturb else None
    progress = run.budget.progress(phase, run.progress["phase_step"], run.progress["elapsed"])
    step = Step(phase, rays, noise, progress, run.progress["phase_step"], run.cfg.seed)
    return run.method.step, (run.models, step)


# ----- the report
def per_step(counters: list[Counter]) -> dict[str, float]:
    total: Counter = Counter()
    for counter in counters:
        total.update(counter)
    return {k: round(v / max(len(counters), 1), 2) for k, v in sorted(total.items())}


def stages_report(steps: list[StepCounts]) -> dict[str, dict]:
    from model.methods.stages import STAGES

    seconds = sum(s.seconds for s in steps) or 1.0
    ops = per_step([s.stage_ops for s in steps])
    syncs = per_step([s.stage_syncs for s in steps])
    return {
        name: {
            "share": round(sum(s.stage_seconds.get(name, 0.0) for s in steps) / seconds, 4),
            "ops": ops.get(name, 0.0),
            "syncs": syncs.get(name, 0.0),
        }
        for name in (*STAGES, OTHER)
    }


def report(
    head: dict, seconds: list[float], steps: list[StepCounts], cuda: bool, rays: int
) -> dict:
    median = statistics.median(seconds)
    return {
        **head,
        "step_ms": {
            "median": round(1e3 * median, 3),
            "min": round(1e3 * min(seconds), 3),
            "max": round(1e3 * max(seconds), 3),
        },
        "rays_per_s": round(rays / median, 1),
        "ops_per_step": statistics.median(s.ops for s in steps),
        "ops_each_step": [s.ops for s in steps],
        "aten_calls_per_step": statistics.median(s.aten_calls for s in steps),
        "host_syncs_per_step": statistics.median(s.syncs for s in steps),
        "host_syncs_each_step": [s.syncs for s in steps],
        "host_syncs_by_op": per_step([s.syncs_by_op for s in steps]),
        "kernels_per_step": statistics.median(s.kernels for s in steps) if cuda else None,
        "cuda_syncs_per_step": statistics.median(s.cuda_syncs for s in steps) if cuda else None,
        "stages": stages_report(steps),
        "compile": None,
    }


def format_report(row: dict) -> str:
    ms = row["step_ms"]
    lines = [
        f"{row['method']}, {row['phase']} phase, profile {row['profile']}, {row['device']}, "
        f"{row['rays']} rays, {row['steps']} steps after {row['warmup']} warm-up, "
        f"{row['threads']} threads" + (", networks compiled" if row["compiled"] else ""),
        f"warm-up {row['warmup_s']:.1f} s" + (" (compiling included)" if row["compiled"] else ""),
        f"step ms    median {ms['median']:.1f}   min {ms['min']:.1f}   max {ms['max']:.1f}   "
        f"rays/s {row['rays_per_s']:,.0f}",
        f"device ops per step  {row['ops_per_step']:g}   (aten calls {row['aten_calls_per_step']:g}"
        + (f", kernels {row['kernels_per_step']:g}" if row["kernels_per_step"] is not None else "")
        + ")",
        f"host syncs per step  {row['host_syncs_per_step']:g}   ("
        + ", ".join(f"{k.removeprefix('aten::')} {v:g}" for k, v in row["host_syncs_by_op"].items())
        + (
            f"; cuda syncs {row['cuda_syncs_per_step']:g}"
            if row["cuda_syncs_per_step"] is not None
            else ""
        )
        + ")",
        f"{'stage':12s} {'share':>7s} {'ops':>8s} {'syncs':>6s}",
    ]
    for name, stage in row["stages"].items():
        lines.append(f"{name:12s} {stage['share']:7.1%} {stage['ops']:8.1f} {stage['syncs']:6.1f}")
    if row["compile"] is not None:
        c = row["compile"]
        lines.append(f"torch.compile: {c['graphs']} graphs, {c['graph_breaks']} graph breaks")
        lines += [f"  - {reason}" for reason in c["break_reasons"]]
    return "\n".join(lines)


def measure(args: argparse.Namespace) -> dict:
    """The run of `args`, warmed up, timed, profiled and (with --compile) explained."""
    import torch

    cuda = bool(args.gpu)
    if cuda and not torch.cuda.is_available():
        raise ValueError("--gpu: PyTorch sees no CUDA device here")
    from workers.config import parse_overrides

    device = torch.device("cuda" if cuda else "cpu")
    overrides = parse_overrides(args.set or [])
    scene = scene_folder(args.scene)
    with tempfile.TemporaryDirectory(prefix="leco-step-") as tmp:
        # the run's own lines (a warm start's) go to stderr: stdout is the report
        with contextlib.redirect_stdout(sys.stderr):
            run = make_run(
                args.method,
                args.profile,
                args.rays,
                scene,
                Path(tmp),
                device,
                args.compile,
                overrides,
            )
            phase = args.phase or default_phase(run.method.phases)
            enter_phase(run, phase, args.at_step)
        step = step_of(run, phase)
        warmup = timed(step, args.warmup, cuda)
        seconds = timed(step, args.steps, cuda)
        steps = count_steps(profile_steps(step, args.steps, cuda), cuda)
        head = {
            "method": args.method,
            "profile": args.profile,
            "phase": phase,
            "device": device.type,
            "rays": run.cfg.global_batch,
            "steps": args.steps,
            "warmup": args.warmup,
            "at_step": args.at_step,
            "threads": torch.get_num_threads(),
            "scene": str(scene),
            "overrides": overrides,
            "compiled": bool(args.compile),
            "warmup_s": round(sum(warmup), 3),
        }
        row = report(head, seconds, steps, cuda, run.cfg.global_batch)
        if args.compile:
            fn, fn_args = method_step(run, phase)
            row["compile"] = graph_breaks(fn, *fn_args)
    return row


def step_command(args: argparse.Namespace) -> int:
    if args.steps < 1 or args.warmup < 0 or args.rays < 1 or args.at_step < 0:
        raise ValueError("--steps and --rays take at least 1, --warmup and --at-step at least 0")
    row = measure(args)
    print(json.dumps(row, indent=1) if args.json else format_report(row))
    return 0


def add_commands(commands: argparse._SubParsersAction) -> None:
    from model.methods import METHODS

    step = commands.add_parser(
        "bench-step",
        help="one method's training step in isolation: time, device ops, host syncs, stages",
    )
    step.add_argument("--method", required=True, help=" | ".join(METHODS))
    step.add_argument("--profile", default="cpu", help="smoke | cpu | paper (default: cpu)")
    step.add_argument("--gpu", action="store_true", help="on CUDA (profiles CUDA activity too)")
    step.add_argument("--rays", type=int, default=256, help="rays per step (default: 256)")
    step.add_argument("--steps", type=int, default=20, help="steps timed, then profiled")
    step.add_argument("--warmup", type=int, default=3, help="steps before the timed ones")
    step.add_argument(
        "--compile",
        action="store_true",
        help="the run's networks compiled (the job setting compile): the warm-up compiles, the "
        "timed and profiled steps run compiled; also the step's graph breaks (torch._dynamo)",
    )
    step.add_argument("--phase", default=None, help="the phase measured (default: the main one)")
    step.add_argument(
        "--at-step",
        type=int,
        default=1000,
        help="the phase's step the measured steps start at (default 1000: past LeCO's online "
        "warm-up and placement anneal)",
    )
    step.add_argument(
        "--scene",
        default=None,
        help=f"scene folder or benchmark scene name (default {DEFAULT_SCENE})",
    )
    step.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override a profile setting, as `leco train --set` (repeatable; rays_per_device "
        "comes from --rays)",
    )
    step.add_argument("--json", action="store_true", help="print JSON instead of a table")
    step.set_defaults(func=step_command)

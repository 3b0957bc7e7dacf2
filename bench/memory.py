"""`leco bench-memory`: the API's memory estimate against a measured peak. For every method and
batch size asked, one process trains a few steps of each phase on a scene (the local backend, one
rank, its final evaluation included) and reports its peak RSS; the table beside it gives the
estimate the API would refuse the job by (model/memory_estimate.py, with the scene's ray length)
and the ratio. The target: no peak above the estimate by more than 25%."""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

TARGET = 1.25  # a measured peak may exceed the estimate by this factor at most


def one_run(scene: Path, run_dir: Path, method: str, profile: str, rays: int, steps: int) -> dict:
    """In this process: `steps` steps of every phase, then the run's evaluation; the peak RSS."""
    from model.methods import get_method
    from workers.config import TrainConfig
    from workers.train.run import run_training

    # each phase's step count, under the setting its method reads it from
    spec = get_method(method)
    phase_steps = {spec.own_key(key): steps for _, key in spec.phase_steps}
    cfg = TrainConfig(
        method=method,
        profile=profile,
        checkpoint_every=10 * steps,
        metrics_every=steps,
        overrides={"rays_per_device": rays, **phase_steps},
    )
    run_training(cfg, scene, run_dir, backend="local")
    return {"peak_rss_mb": peak_rss_mb()}


def peak_rss_mb() -> float:
    """This process's peak resident set. /proc's VmHWM belongs to the address space exec made;
    getrusage's ru_maxrss also keeps the parent's peak at the fork (a child of a 10 GB process
    starts at 10 GB)."""
    status = Path("/proc/self/status")
    if status.exists():
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def scene_shape(scene: Path) -> tuple[int, float]:
    """What the estimate reads off a scene: its images and its rays' mean share of the box's
    diagonal (as scene info records it for the API)."""
    from model.scenes import load_scene
    from model.scenes.info import ray_segment_stats

    loaded = load_scene(scene)
    return loaded.num_images, ray_segment_stats(loaded)["mean_diagonal_fraction"]


def estimate_mb(shape: tuple[int, float], method: str, profile: str, rays: int) -> float:
    from model.memory_estimate import estimate_peak_bytes
    from workers.config import TrainConfig

    cfg = TrainConfig(method=method, profile=profile, overrides={"rays_per_device": rays})
    return estimate_peak_bytes(method, cfg.resolved_profile(), *shape)["total"] / 2**20


def memory_command(args: argparse.Namespace) -> int:
    from model.methods import METHODS

    methods = args.methods.split(",") if args.methods else list(METHODS)
    sizes = [int(x) for x in args.rays.split(",")]
    scene = Path(args.scene).resolve()
    shape = scene_shape(scene)
    rows = []
    print(f"{'method':15s} {'rays':>6s} {'estimate MiB':>13s} {'peak RSS MiB':>13s} {'ratio':>6s}")
    for method in methods:
        for rays in sizes:
            with tempfile.TemporaryDirectory(prefix="leco-memory-") as tmp:
                child = subprocess.run(
                    [sys.executable, "-m", "bench.memory", "--one", str(scene), tmp]
                    + [method, args.profile, str(rays), str(args.steps)],
                    capture_output=True,
                    text=True,
                )
            if child.returncode != 0:
                print(child.stderr[-2000:], file=sys.stderr)
                return 1
            peak = json.loads(child.stdout.strip().splitlines()[-1])["peak_rss_mb"]
            estimate = estimate_mb(shape, method, args.profile, rays)
            rows.append(
                {"method": method, "rays": rays, "estimate_mb": estimate, "peak_rss_mb": peak}
            )
            print(f"{method:15s} {rays:6d} {estimate:13,.0f} {peak:13,.0f} {peak / estimate:6.2f}")
    over = [r for r in rows if r["peak_rss_mb"] > TARGET * r["estimate_mb"]]
    print(f"{len(rows) - len(over)} of {len(rows)} within the estimate + {TARGET - 1:.0%}")
    if args.out:
        Path(args.out).write_text(json.dumps(rows, indent=1) + "\n")
    return 0 if not over else 1


def add_commands(commands: argparse._SubParsersAction) -> None:
    memory = commands.add_parser(
        "bench-memory", help="the API's memory estimate against each method's measured peak RSS"
    )
    memory.add_argument("--scene", required=True, help="scene folder")
    memory.add_argument("--methods", default="", help="comma-separated (default: every method)")
    memory.add_argument("--profile", default="cpu", help="smoke | cpu | paper (default: cpu)")
    memory.add_argument("--rays", default="256,1024", help="rays_per_device values to measure")
    memory.add_argument("--steps", type=int, default=20, help="steps of each phase per run")
    memory.add_argument("--out", default=None, help="also write the rows as JSON here")
    memory.set_defaults(func=memory_command)


if __name__ == "__main__":
    if sys.argv[1:2] == ["--one"]:
        scene, run_dir, method, profile, rays, steps = sys.argv[2:8]
        record = one_run(Path(scene), Path(run_dir), method, profile, int(rays), int(steps))
        print(json.dumps(record))

"""`leco bench-memory`: the API's memory estimate against a measured peak. For every method and
batch size asked, one process trains a few steps of each phase on a scene (the local backend, one
rank, its final evaluation included) and reports its peak RSS; the table beside it gives the
estimate the API would refuse the job by (model/memory_estimate.py, with the scene's ray length)
and the ratio. The target: no peak above the estimate by more than 25%. With `--frames WxH,...`
it measures instead what a render or an export holds for one frame of each size (a process a
frame): the peak against `estimate_frames_bytes`, and the bytes a pixel costs between the sizes."""

from __future__ import annotations

import argparse
import ctypes
import json
import resource
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from workers.config import TrainConfig

TARGET = 1.25  # a measured peak may exceed the estimate by this factor at most


def run_config(
    method: str, profile: str, rays: int, steps: int, overrides: dict | None = None
) -> TrainConfig:
    """The config of a measured run: `overrides` (--set) on the profile, then the batch size and
    `steps` steps of every phase (--rays and --steps win over --set)."""
    from model.methods import get_method
    from workers.config import TrainConfig

    # each phase's step count, under the setting its method reads it from
    spec = get_method(method)
    phase_steps = {spec.own_key(key): steps for _, key in spec.phase_steps}
    return TrainConfig(
        method=method,
        profile=profile,
        checkpoint_every=10 * steps,
        metrics_every=steps,
        overrides={**(overrides or {}), "rays_per_device": rays, **phase_steps},
    )


def one_run(scene: Path, run_dir: Path, cfg: TrainConfig) -> dict:
    """In this process: the run `cfg` (run_config: a few steps of every phase), then its
    evaluation; the peak RSS."""
    from workers.train.run import run_training

    run_training(cfg, scene, run_dir, backend="local")
    return {"peak_rss_mb": peak_rss_mb()}


def one_frame(scene: Path, cfg: TrainConfig, width: int, height: int) -> dict:
    """In this process: one frame of `width` x `height` through a method's networks (as built:
    the samplers take their full budget), kept as a render and an export keep it (colours as bytes,
    the depth range, every pixel's surface point); the peak RSS."""
    from dataclasses import replace

    import torch

    from model.scenes import load_scene
    from workers.models import build_models
    from workers.render.frames import appearance_row, render_frame
    from workers.renderer import depth_range, to_uint8
    from workers.trained import Trained

    loaded = load_scene(scene)
    spec = cfg.method_for_run()
    device = torch.device("cpu")
    models = build_models(spec, loaded.num_images, loaded.bounds.aabb, 0)
    spec.start_phase(models, "main", True, device, lambda text: None)  # its sampler, as built
    trained = Trained(cfg, loaded, spec, models.eval(), device)
    cameras = loaded.splits["val"].cameras
    scale = torch.tensor([width, height, width, height]) / torch.stack(
        [cameras.width, cameras.height, cameras.width, cameras.height], -1
    )
    n = len(cameras)
    sized = replace(
        cameras,
        intrinsics=cameras.intrinsics * scale,
        width=torch.full((n,), width),
        height=torch.full((n,), height),
    )
    setup_peak = peak_rss_mb()
    before = restart_peak()
    frame = render_frame(trained, sized, 0, appearance_row(trained, "mean"))
    to_uint8(frame.rgb).numpy()
    depth_range(frame)
    frame.surface_points(0.0)
    frame_peak = peak_rss_mb()
    return {"peak_rss_mb": max(setup_peak, frame_peak), "frame_mb": frame_peak - before}


def peak_rss_mb() -> float:
    """This process's peak resident set. /proc's VmHWM belongs to the address space exec made;
    getrusage's ru_maxrss also keeps the parent's peak at the fork (a child of a 10 GB process
    starts at 10 GB)."""
    peak = proc_status_mb("VmHWM")
    return peak if peak is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def proc_status_mb(key: str) -> float | None:
    """A size /proc/self/status reports (VmHWM, VmRSS) in MiB; None without /proc."""
    status = Path("/proc/self/status")
    if not status.exists():
        return None
    for line in status.read_text().splitlines():
        if line.startswith(f"{key}:"):
            return int(line.split()[1]) / 1024
    return None


def restart_peak() -> float:
    """Hands the heap's free pages back and restarts the peak at the RSS now (Linux's clear_refs
    5), which it returns (MiB). Without it a frame's buffers land in pages an earlier step freed
    and its cost hides under that step's peak: 800x600 measured -11 to 335 bytes a pixel."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass  # no glibc or no /proc: the frame's cost is measured over the earlier peak
    rss = proc_status_mb("VmRSS")
    return rss if rss is not None else peak_rss_mb()


def scene_shape(scene: Path) -> tuple[int, float]:
    """What the estimate reads off a scene: its images and its rays' mean share of the box's
    diagonal (as scene info records it for the API)."""
    from model.scenes import load_scene
    from model.scenes.info import ray_segment_stats

    loaded = load_scene(scene)
    return loaded.num_images, ray_segment_stats(loaded)["mean_diagonal_fraction"]


def estimate_mb(shape: tuple[int, float], cfg: TrainConfig) -> float:
    from model.memory_estimate import estimate_peak_bytes

    return estimate_peak_bytes(cfg.method, cfg.resolved_profile(), *shape)["total"] / 2**20


def child_peak(*words: str) -> dict | None:
    """`python -m bench.memory WORDS` in a fresh process: what it measured (its peak RSS, MiB, and
    for a frame the frame's own peak over the RSS before it), or None (its error printed) when it
    failed."""
    child = subprocess.run(
        [sys.executable, "-m", "bench.memory", *words], capture_output=True, text=True
    )
    if child.returncode != 0:
        print(child.stderr[-2000:], file=sys.stderr)
        return None
    return json.loads(child.stdout.strip().splitlines()[-1])


def frames_command(
    args: argparse.Namespace, methods: list[str], scene: Path, overrides: dict
) -> int:
    from model.memory_estimate import FRAME_BYTES_PER_PIXEL, estimate_frames_bytes
    from workers.config import TrainConfig

    images = scene_shape(scene)[0]
    sizes = [tuple(int(x) for x in size.split("x")) for size in args.frames.split(",")]
    rows = []
    print(
        f"{'method':15s} {'frame':>10s} {'estimate MiB':>13s} {'peak RSS MiB':>13s} "
        f"{'ratio':>6s} {'frame MiB':>9s} {'bytes/pixel':>12s}"
    )
    for method in methods:
        cfg = TrainConfig(method=method, profile=args.profile, overrides=overrides)
        profile = cfg.resolved_profile()
        previous: tuple[int, float] | None = None
        for width, height in sizes:
            measured = child_peak(
                "--one-frame", str(scene), cfg.model_dump_json(), str(width), str(height)
            )
            if measured is None:
                return 1
            peak, frame = measured["peak_rss_mb"], measured["frame_mb"]
            pixels = width * height
            estimate = estimate_frames_bytes(method, profile, images, pixels)["total"] / 2**20
            # what a pixel costs: the frames' own peaks (each over the RSS before it) between sizes
            slope: float | None = (
                (frame - previous[1]) * 2**20 / (pixels - previous[0])
                if previous and pixels != previous[0]
                else None
            )
            previous = (pixels, frame)
            rows.append(
                {
                    "method": method,
                    "width": width,
                    "height": height,
                    "estimate_mb": estimate,
                    "peak_rss_mb": peak,
                    "frame_mb": frame,
                    "bytes_per_pixel": slope,
                }
            )
            print(
                f"{method:15s} {f'{width}x{height}':>10s} {estimate:13,.0f} {peak:13,.0f} "
                f"{peak / estimate:6.2f} {frame:9,.0f} {'' if slope is None else f'{slope:12,.0f}'}"
            )
    over = [r for r in rows if r["peak_rss_mb"] > TARGET * r["estimate_mb"]]
    print(
        f"{len(rows) - len(over)} of {len(rows)} within the estimate + {TARGET - 1:.0%} "
        f"(the estimate counts {FRAME_BYTES_PER_PIXEL} bytes a pixel)"
    )
    if args.out:
        Path(args.out).write_text(json.dumps(rows, indent=1) + "\n")
    return 0 if not over else 1


def memory_command(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from model.methods import METHODS
    from workers.config import TrainConfig, parse_overrides

    methods = args.methods.split(",") if args.methods else list(METHODS)
    try:
        overrides = parse_overrides(args.set or [])
        for method in methods:  # a bad key or value fails here, before any run
            TrainConfig(method=method, profile=args.profile, overrides=overrides).resolved_profile()
    except (ValueError, ValidationError) as error:
        raise SystemExit(f"leco bench-memory: {error}") from None
    if args.frames:
        return frames_command(args, methods, Path(args.scene).resolve(), overrides)
    sizes = [int(x) for x in args.rays.split(",")]
    scene = Path(args.scene).resolve()
    shape = scene_shape(scene)
    rows: list[dict] = []
    print(f"{'method':15s} {'rays':>6s} {'estimate MiB':>13s} {'peak RSS MiB':>13s} {'ratio':>6s}")
    for method in methods:
        for rays in sizes:
            cfg = run_config(method, args.profile, rays, args.steps, overrides)
            with tempfile.TemporaryDirectory(prefix="leco-memory-") as tmp:
                measured = child_peak("--one", str(scene), tmp, cfg.model_dump_json())
            if measured is None:
                return 1
            peak = measured["peak_rss_mb"]
            estimate = estimate_mb(shape, cfg)
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
    memory.add_argument(
        "--frames", default="", help="WxH,... : measure a frame of each size instead of training"
    )
    memory.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override a profile setting in every run and its estimate, as `leco train --set` "
        "(repeatable; rays_per_device and the phases' steps come from --rays and --steps)",
    )
    memory.add_argument("--out", default=None, help="also write the rows as JSON here")
    memory.set_defaults(func=memory_command)


def child_main(argv: list[str]) -> dict:
    """A measuring child (child_peak's words): the run or frame of the config it is given, as JSON
    (the parent's TrainConfig, --set included)."""
    from workers.config import TrainConfig

    if argv[:1] == ["--one-frame"]:
        scene, config, width, height = argv[1:5]
        cfg = TrainConfig.model_validate_json(config)
        return one_frame(Path(scene), cfg, int(width), int(height))
    if argv[:1] == ["--one"]:
        scene, run_dir, config = argv[1:4]
        return one_run(Path(scene), Path(run_dir), TrainConfig.model_validate_json(config))
    raise SystemExit(f"bench.memory: expected --one or --one-frame, got {argv[:1]}")


if __name__ == "__main__":
    print(json.dumps(child_main(sys.argv[1:])))

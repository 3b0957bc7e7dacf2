"""`leco bench-scale`: large scenes measured. Train a few steps with N data-parallel Ray workers on
each scene given, twice on the first (the first start builds its pixel caches, the second reuses
them), and print per run: images, training pixels, store build (or open) time, time to first step,
each rank's peak RSS, and rays/s.

Each start is its own process with its own local Ray, so a rank's peak RSS is that run's alone. Only
training is timed: the final evaluation is not run (rendering 20 validation views of 640x480 on a
CPU takes longer than the measurement itself)."""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def one_start(
    scene: Path, run_dir: Path, method: str, profile: str, workers: int, steps: int
) -> dict:
    """In this process: train `steps` main steps, return what the ranks and the metrics recorded."""
    import numpy as np

    from model.scenes import load_scene
    from workers.config import TrainConfig
    from workers.train.run import ensure_ray, fit_with_ray, prepare_run_dir
    from workers.train.sinks import read_metrics

    started = time.time()
    scene, run_dir = scene.resolve(), run_dir.resolve()  # Ray's workers run in folders of their own
    cfg = TrainConfig(
        method=method,
        profile=profile,
        workers=workers,
        checkpoint_every=10 * steps,
        metrics_every=5,
        overrides={"main_steps": steps, "occupancy.steps": steps},
    )
    ensure_ray(max(2, workers))
    ray_up = time.time()
    prepare_run_dir(cfg, scene, run_dir)
    fit_with_ray(cfg, scene, run_dir, None, None)
    ranks = [
        json.loads((run_dir / "workers" / f"rank{r}.json").read_text()) for r in range(workers)
    ]
    rows = [m for m in read_metrics(run_dir / "metrics.jsonl") if m.get("phase") == "main"]
    views = load_scene(scene).train
    return {
        "scene": str(scene),
        "images": len(views),
        "train_pixels": views.num_pixels,
        "ray_up_s": ray_up - started,
        "scene_load_s": max(r["scene_loaded_at"] - r["started_at"] for r in ranks),
        "pixels_ready_s": max(r["pixels_ready_at"] - r["scene_loaded_at"] for r in ranks),
        "first_step_s": max(r["first_step_at"] for r in ranks) - started,
        "peak_rss_mb": [round(r["peak_memory_mb"]) for r in ranks],
        # The first window holds the first steps' one-off costs (allocator warm-up): left out when
        # there are more.
        "rays_per_s": float(np.mean([m["rays_per_s"] for m in (rows[1:] or rows)])),
        "steps": steps,
        "workers": workers,
        "method": method,
        "profile": profile,
    }


def scale_command(args: argparse.Namespace) -> int:
    scenes = [Path(s) for s in args.scene]
    cache = Path(args.cache or tempfile.mkdtemp(prefix="leco-scale-cache-"))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = []
    plan = [(scenes[0], "first start"), (scenes[0], "second start (stores reused)")]
    plan += [(scene, "first start") for scene in scenes[1:]]
    for i, (scene, label) in enumerate(plan):
        if label == "first start":
            shutil.rmtree(cache, ignore_errors=True)  # every first start builds its stores
        run_dir = out / f"run{i}"
        shutil.rmtree(run_dir, ignore_errors=True)
        command = [
            sys.executable,
            "-m",
            "bench.scale",
            "--one",
            str(scene),
            str(run_dir),
            args.method,
            args.profile,
            str(args.workers),
            str(args.steps),
        ]
        done = subprocess.run(
            command,
            env={**os.environ, "LECO_PIXEL_CACHE": str(cache)},
            capture_output=True,
            text=True,
        )
        if done.returncode != 0:
            raise SystemExit(f"leco bench-scale: the run on {scene} failed:\n{done.stderr[-3000:]}")
        result = {"start": label, **json.loads(done.stdout.strip().splitlines()[-1])}
        results.append(result)
        print(format_row(result), flush=True)
    (out / "scale.json").write_text(json.dumps(results, indent=1))
    return 0


def format_row(r: dict) -> str:
    return (
        f"{Path(r['scene']).name:>12} {r['start']:<30} {r['images']:>6,} images "
        f"{r['train_pixels'] / 1e6:7.1f} M px  pixels ready {r['pixels_ready_s']:6.1f} s  first "
        f"step {r['first_step_s']:6.1f} s  peak RSS {'/'.join(map(str, r['peak_rss_mb']))} MB  "
        f"{r['rays_per_s']:7.0f} rays/s"
    )


def add_commands(commands) -> None:
    from model.methods import METHODS

    scale = commands.add_parser(
        "bench-scale",
        help="time to first step, per-rank peak RSS and rays/s on large scenes; the first scene is "
        "started twice",
    )
    scale.add_argument(
        "--scene",
        action="append",
        required=True,
        help="scene folder; repeat to compare (the first is started twice)",
    )
    scale.add_argument("--out", required=True, help="folder for the runs and scale.json")
    scale.add_argument("--method", default="switch", choices=list(METHODS))
    scale.add_argument("--profile", default="cpu")
    scale.add_argument("--workers", type=int, default=2)
    scale.add_argument(
        "--steps", type=int, default=40, help="main-phase steps per run (and phase-1 steps)"
    )
    scale.add_argument(
        "--cache", default=None, help="pixel cache folder (default: a new temporary one)"
    )
    scale.set_defaults(func=scale_command)


if __name__ == "__main__":
    if sys.argv[1:2] == ["--one"]:
        scene, run_dir, method, profile, workers, steps = sys.argv[2:8]
        print(
            json.dumps(
                one_start(Path(scene), Path(run_dir), method, profile, int(workers), int(steps))
            )
        )

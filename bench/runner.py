"""Running the variants back to back, each in its own process, at the same profile, seed and budget.

A run folder that already holds a finished run of the same spec is reused, so an interrupted
benchmark continues where it stopped instead of starting over."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from bench.variants import Variant
from model.errors import Failed
from model.profiles import MAX_STEPS
from workers.config import TrainConfig
from workers.train.sinks import read_metrics

UNBOUNDED_STEPS = MAX_STEPS  # with a budget, the clock ends the run, not a step count
CHECKPOINT_EVERY = 1000  # checkpoints are not training time, but they are wall time: keep them rare


class BenchError(Failed):
    pass


@dataclass
class Plan:
    scene: Path
    profile: str
    out: Path
    budget_min: float | None
    seeds: list[int]
    eval_every_s: float
    eval_views: int
    backend: str = "local"
    workers: int = 1
    use_gpu: bool = False
    overrides: dict | None = None
    downscale: int | None = None  # None: the scene's own scale


def config_for(variant: Variant, plan: Plan, seed: int) -> TrainConfig:
    overrides = {**(plan.overrides or {}), **variant.overrides}
    if plan.budget_min is not None:
        overrides["main_steps"] = UNBOUNDED_STEPS
    return TrainConfig(
        method=variant.method,
        profile=plan.profile,
        overrides=overrides,
        budget_min=plan.budget_min,
        seed=seed,
        eval_every_s=plan.eval_every_s,
        eval_views=plan.eval_views,
        checkpoint_every=CHECKPOINT_EVERY,
        workers=plan.workers,
        use_gpu=plan.use_gpu,
        downscale=plan.downscale,
    )


def run_dir_for(plan: Plan, variant: Variant, seed: int) -> Path:
    return plan.out / "runs" / f"{variant.name}-seed{seed}"


def finished(run_dir: Path, cfg: TrainConfig, scene: Path) -> dict | None:
    """The summary of a finished run of exactly this spec in run_dir, else None (a different spec is
    an error)."""
    record, summary = run_dir / "run.json", run_dir / "summary.json"
    if not record.exists():
        return None
    old = json.loads(record.read_text())
    if (old.get("config"), old.get("scene")) != (cfg.model_dump(mode="json"), str(scene.resolve())):
        raise BenchError(f"{run_dir} holds a run with another config or scene: choose a new --out")
    return json.loads(summary.read_text()) if summary.exists() else None


@contextmanager
def stop_on_sigterm() -> Iterator[None]:
    """SIGTERM (`kill`) ends the benchmark as Ctrl-C does, so the run it is waiting on is stopped
    too rather than left training alone (and slowing whatever runs next)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def wait_or_stop(child: subprocess.Popen) -> int:
    """The child's exit code; if the wait is interrupted the child is stopped first."""
    try:
        return child.wait()
    except BaseException:
        child.terminate()
        try:
            child.wait(timeout=30)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
        raise


def run_variant(variant: Variant, plan: Plan, seed: int, log=print) -> dict:
    cfg = config_for(variant, plan, seed)
    run_dir = run_dir_for(plan, variant, seed)
    summary = finished(run_dir, cfg, plan.scene)
    if summary is not None:
        log(f"[bench] {variant.name} seed {seed}: finished earlier, reusing {run_dir}")
    else:
        run_dir.mkdir(parents=True, exist_ok=True)
        spec = {
            "config": cfg.model_dump(mode="json"),
            "scene": str(plan.scene),
            "run_dir": str(run_dir),
            "backend": plan.backend,
        }
        log(
            f"[bench] {variant.name} seed {seed}: training ({cfg.budget_min or 'no'} min budget) "
            f"-> {run_dir}"
        )
        started = time.perf_counter()
        with (run_dir / "bench.log").open("w") as out, stop_on_sigterm():
            child = subprocess.Popen(
                [sys.executable, "-m", "bench.run_one", json.dumps(spec)],
                stdout=out,
                stderr=subprocess.STDOUT,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )
            code = wait_or_stop(child)
        if code != 0:
            tail = (run_dir / "bench.log").read_text().strip().splitlines()[-5:]
            raise BenchError(
                f"{variant.name} (seed {seed}) failed with exit code {code}; the last lines of "
                f"{run_dir / 'bench.log'}:\n" + "\n".join(tail)
            )
        summary = json.loads((run_dir / "summary.json").read_text())
        log(
            f"[bench] {variant.name} seed {seed}: done in {time.perf_counter() - started:.0f} s, "
            f"val PSNR {summary['val']['psnr']:.2f}"
        )
    return {
        "variant": variant.name,
        "method": variant.method,
        "label": variant.label,
        "ablation": variant.ablation,
        "ladder": variant.ladder,
        "sweep": variant.sweep,
        "seed": seed,
        "run_dir": str(run_dir),
        "summary": summary,
        "curve": curve(read_metrics(run_dir / "metrics.jsonl")),
    }


def curve(rows: list[dict]) -> list[dict]:
    """The run's periodic validation points and per-step series the report and plots need."""
    keep = (
        "step",
        "phase",
        "phase_step",
        "wall_time_s",
        "val_psnr",
        "val_ssim",
        "occupancy_f1",
        "occupancy_precision",
        "occupancy_recall",
        "fraction_empty",
        "samples_per_ray",
        "rays_per_s",
        "psnr",
    )
    return [{k: r.get(k) for k in keep if r.get(k) is not None} for r in rows]

"""`leco train` and `leco eval`: runs from the command line with a one-line progress bar."""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import TYPE_CHECKING, TextIO

if TYPE_CHECKING:
    from workers.config import TrainConfig


def format_progress(row: dict, cfg: TrainConfig) -> str:
    """[phase] step s/total (p%) | rays/s | PSNR | ETA, from the latest metrics record."""
    phase, phase_step = row.get("phase", "?"), int(row.get("phase_step", 0))
    total = cfg.phase_steps(phase) if phase in cfg.phases else phase_step
    later = (
        sum(cfg.phase_steps(p) for p in cfg.phases[cfg.phases.index(phase) + 1 :])
        if phase in cfg.phases
        else 0
    )
    rays = row.get("rays_per_s") or 0.0
    seconds_per_step = cfg.global_batch / rays if rays else 0.0
    eta = (total - phase_step + later) * seconds_per_step
    psnr = row.get("psnr")
    return (
        f"[{phase}] step {phase_step}/{total} ({100 * phase_step / max(total, 1):.0f}%) | "
        f"{rays:,.0f} rays/s | PSNR {psnr:.2f} | ETA {int(eta // 60)}m{int(eta % 60):02d}s"
        if psnr is not None
        else f"[{phase}] step {phase_step}/{total} | {rays:,.0f} rays/s | ETA "
        f"{int(eta // 60)}m{int(eta % 60):02d}s"
    )


class ProgressPrinter:
    """Rewrites one line on a terminal; elsewhere prints a line at most every `every_s` seconds."""

    def __init__(
        self, cfg: TrainConfig, stream: TextIO | None = None, every_s: float = 10.0
    ) -> None:
        # sys.stderr looked up now, not at import: it may have been replaced since (pytest,
        # redirects).
        self.cfg, self.stream, self.every_s = cfg, stream or sys.stderr, every_s
        self.tty = self.stream.isatty()
        self.last_line, self.last_time = "", 0.0

    def __call__(self, row: dict) -> None:
        line = format_progress(row, self.cfg)
        if line == self.last_line:
            return
        if self.tty:
            self.stream.write("\r" + line.ljust(len(self.last_line)))
        elif time.monotonic() - self.last_time >= self.every_s:
            self.stream.write(line + "\n")
            self.last_time = time.monotonic()
        self.stream.flush()
        self.last_line = line

    def close(self) -> None:
        if self.tty and self.last_line:
            self.stream.write("\n")


def train_command(args: argparse.Namespace) -> int:
    from workers.config import TrainConfig, parse_overrides
    from workers.train.run import run_training

    cfg = TrainConfig(
        method=args.method,
        profile=args.profile,
        overrides=parse_overrides(args.set or []),
        workers=args.workers,
        use_gpu=args.gpu,
        budget_min=args.budget_min,
        seed=args.seed,
        checkpoint_every=args.checkpoint_every,
        eval_every_s=args.eval_every_s,
        downscale=args.downscale,
        compile=args.compile,
    )
    progress = ProgressPrinter(cfg)
    try:
        summary = run_training(
            cfg, args.scene, args.out, backend=args.backend, on_progress=progress
        )
    finally:
        progress.close()
    print(
        json.dumps(
            {
                k: summary[k]
                for k in (
                    "method",
                    "profile",
                    "wall_time_s",
                    "steps",
                    "rays_per_s",
                    "samples_per_ray",
                    "occupancy",
                    "val",
                    "peak_memory_mb",
                )
            },
            indent=2,
        )
    )
    return 0


def eval_command(args: argparse.Namespace) -> int:
    from workers.train.evaluate import evaluate_run

    print(json.dumps(evaluate_run(args.run), indent=2))
    return 0


def add_commands(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from model.methods import METHODS

    train = commands.add_parser(
        "train", help=f"train a scene with {' | '.join(METHODS)} (Ray Train workers)"
    )
    train.add_argument("--scene", required=True, help="scene folder (any supported format)")
    train.add_argument("--method", required=True, choices=list(METHODS))
    train.add_argument("--profile", default="cpu", help="smoke | cpu | paper (default: cpu)")
    train.add_argument("--out", required=True, help="run folder; an unfinished run there resumes")
    train.add_argument("--workers", type=int, default=1, help="data-parallel workers (1-8)")
    train.add_argument("--gpu", action="store_true", help="one GPU per worker (nccl)")
    train.add_argument(
        "--budget-min", type=float, default=None, help="wall-clock budget in minutes"
    )
    train.add_argument("--seed", type=int, default=0)
    train.add_argument(
        "--downscale",
        type=int,
        default=None,
        help="integer factor for images and intrinsics, in training and evaluation alike (default: "
        "the scene's own scale; the paper uses 4 on Mega-NeRF scenes)",
    )
    train.add_argument(
        "--checkpoint-every", type=int, default=200, help="steps between checkpoints"
    )
    train.add_argument(
        "--eval-every-s",
        type=float,
        default=None,
        help="validation PSNR/SSIM every this many seconds of training time (not counted in it)",
    )
    train.add_argument(
        "--compile",
        action="store_true",
        help="compile the networks with torch.compile (inductor); the compiling counts as "
        "training time (a CPU needs a C++ compiler)",
    )
    train.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override a profile setting, e.g. --set occupancy.steps=200 (repeatable; `leco "
        "settings` lists them)",
    )
    train.add_argument(
        "--backend",
        default="ray",
        choices=["ray", "local"],
        help="ray (default): Ray Train workers; local: one process without Ray",
    )
    train.set_defaults(func=train_command)

    evaluate = commands.add_parser(
        "eval", help="evaluate a finished run again (PSNR, SSIM, LPIPS VGG/Alex, occupancy)"
    )
    evaluate.add_argument("--run", required=True, help="run folder written by leco train")
    evaluate.set_defaults(func=eval_command)

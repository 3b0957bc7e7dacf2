"""The per-rank training loop: phases, data-parallel steps, non-finite skipping, checkpoints,
metrics.

Every rank draws its disjoint share of the same global ray batch, computes its loss on it, and the
gradients are averaged (plain data parallel). A step whose loss or gradients are non-finite on any
rank is skipped on every rank; too many in a row end the run with a reason (the last good checkpoint
stays). What a checkpoint holds is checkpoint.py's; the budget, budget.py's; the metrics row,
window.py's; rank 0's reports, reporter.py's."""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import threading
import time
from pathlib import Path

import torch

from model.errors import Failed
from model.methods.base import Step
from model.methods.parts import Parts
from model.methods.stages import stage
from model.render.noise import Noise
from model.scenes import load_scene
from workers.config import TrainConfig
from workers.memory import SavedTensorBytes
from workers.models import LiveNetworks, PhaseObjects, build_models, build_optimizer
from workers.pixels import attach_pixel_caches
from workers.store import RunStore
from workers.train.budget import Budget
from workers.train.checkpoint import (
    STATE_FILE,
    TrainingState,
    generator_states,
    load_snapshot,
    restore_draws,
    restore_networks,
    save_final,
    snapshot,
)
from workers.train.compiled import check_can_compile, compile_modules
from workers.train.distributed import any_rank, any_rank_each, any_rank_tensor, average_gradients
from workers.train.lent_generator import lent
from workers.train.nonfinite import NonfiniteStreak, nonfinite
from workers.train.periodic_eval import PeriodicEval
from workers.train.ray_batches import ray_batches
from workers.train.reporter import StoreReporter
from workers.train.session import Session
from workers.train.sinks import JsonlSink
from workers.train.validation import write_validation_renders
from workers.train.window import MetricsWindow, peak_memory_mb


class NonFiniteRun(Failed):
    """Too many consecutive steps were not finite (`max_nonfinite_steps`)."""


class StoreFailed(Failed):
    """Rank 0 could not write to the launcher's store (StoreWriteError); every rank stops at a step
    boundary."""

    def __init__(self, message: str, retryable: bool = False):
        super().__init__(message)
        self.retryable = retryable


class RunStopped(Failed):
    """The launcher asked the run to stop (a cancel, a lost lease); it stopped at a step boundary
    after a checkpoint."""


class RankRun:
    def __init__(
        self,
        cfg: TrainConfig,
        scene_dir: Path,
        run_dir: Path,
        session: Session,
        device: torch.device,
        store: RunStore | None = None,
    ):
        self.cfg, self.run_dir, self.session, self.device = cfg, Path(run_dir), session, device
        # wall-clock marks of this rank's start (workers/rank<r>.json)
        self.timeline = {"started_at": time.time()}
        self.scene = load_scene(scene_dir, downscale=cfg.downscale)
        self.timeline["scene_loaded_at"] = time.time()
        attach_pixel_caches(self.scene)
        self.timeline["pixels_ready_at"] = time.time()
        self.aabb = self.scene.bounds.aabb
        self.profile = cfg.resolved_profile()
        if cfg.compile:
            check_can_compile(device)
        method = cfg.method_for_run()
        models = build_models(method, self.scene.num_images, self.aabb, cfg.seed).to(device)
        method.to(device)
        sampler = ray_batches(
            self.scene.train,
            self.aabb,
            cfg.global_batch,
            cfg.seed,
            session.rank,
            session.world_size,
            device,
            cfg.pixels_on_device_max_mb,
        )
        # Per-rank seeds, on the device the samplers draw on (a CPU generator cannot fill CUDA
        # tensors).
        generator = torch.Generator(device=device).manual_seed(cfg.seed * 7919 + session.rank)
        progress = {"phase": cfg.phases[0], "phase_step": 0, "step": 0, "elapsed": {}}
        progress.update(steps={}, nonfinite=0)
        self.state = TrainingState(progress, models, method, sampler, generator)
        self.method, self.models = method, models
        self.live = LiveNetworks(method, models, self.aabb, device)
        self.budget = Budget(cfg.budget_min, method)
        self.nonfinite = NonfiniteStreak(0, device)
        self.phase_objects: PhaseObjects | None = None
        self.lr_ramp_steps = 0
        self.activation_mb: float | None = None
        rank0 = session.rank == 0
        self.sink = JsonlSink(self.run_dir / "metrics.jsonl") if rank0 else None
        self.report = StoreReporter(store if rank0 else None)
        self.periodic = (
            PeriodicEval(cfg.eval_every_s, self.scene, cfg.eval_views, cfg.val_appearance_steps)
            if rank0 and cfg.eval_every_s
            else None
        )

    @property
    def progress(self) -> dict:
        return self.state.progress

    # ----- checkpoints
    # -------------------------------------------------------------------------------
    def save_checkpoint(self, metrics: dict) -> None:
        generators = generator_states(self.state.generator, self.session.world_size)
        self.progress["nonfinite"] = self.nonfinite.running()
        if self.session.rank != 0:
            self.session.report(metrics, None)
            return
        saved = snapshot(self.state, self.current_phase().optimizer, generators, self.cfg)
        with tempfile.TemporaryDirectory() as tmp:
            torch.save(saved, Path(tmp) / STATE_FILE)
            step = self.progress["step"]
            name = f"checkpoint-step{step:07d}.pt"
            phase = self.progress["phase"]
            self.report(
                "artifact", "checkpoint", Path(tmp) / STATE_FILE, name=name, phase=phase, step=step
            )
            self.session.report(metrics, Path(tmp))

    def restore(self) -> bool:
        with self.session.resume_dir() as path:
            if path is None:
                return False
            saved = load_snapshot(Path(path))
        restore_networks(self.state, saved, self.device)
        self.nonfinite = NonfiniteStreak(self.progress["nonfinite"], self.device)
        self.start_phase(self.progress["phase"])
        restore_draws(self.state, saved, self.current_phase().optimizer, self.session.rank)
        return True

    def check_store(self) -> None:
        if any_rank(self.report.error is not None, self.device):
            raise StoreFailed(
                f"the run stopped because its store could not be written: {self.report.error}"
                if self.report.error
                else "rank 0 could not write to the run's store",
                self.report.retryable,
            )

    # ----- phases
    # ------------------------------------------------------------------------------------
    def current_phase(self) -> PhaseObjects:
        if self.phase_objects is None:
            raise RuntimeError("no phase started: start_phase makes the optimizer")
        return self.phase_objects

    def start_phase(self, phase: str, fresh: bool = False) -> None:
        """Optimizer and frozen parts of a phase; `fresh` when the phase begins now (not on a
        resume)."""
        log = lambda text: (
            print(f"[{self.cfg.method}] {text}", flush=True) if self.session.rank == 0 else None
        )
        # Before the optimizer: the method may copy weights into the phase's networks or freeze some
        # of them.
        self.method.start_phase(self.models, phase, fresh, self.device, log)
        if self.cfg.compile:
            compile_modules(self.method.compiled_modules(self.models, phase))
        self.phase_objects = build_optimizer(self.method, self.models, phase)
        self.lr_ramp_steps = self.method.lr_ramp_steps(phase)
        self.report("phase_started", phase)

    def budget_left(self, phase: str) -> bool:
        return self.budget.left(phase, self.progress["elapsed"], self.progress["phase_step"])

    def run_phase(self, phase: str) -> None:
        objects = self.current_phase()
        total = self.method.phase_steps(phase)
        window = MetricsWindow(self.cfg.global_batch)
        while self.progress["phase_step"] < total and not self.stopped_or_spent(phase):
            started = time.perf_counter()
            parts = self.train_step(phase, objects)
            # compute only: checkpoints and renders are not training time
            seconds = time.perf_counter() - started
            before = sum(self.progress["elapsed"].values())
            self.progress["elapsed"][phase] = self.progress["elapsed"].get(phase, 0.0) + seconds
            # Rank 0's own view of the end is exact: any rank's spent budget stops every rank
            # (stopped_or_spent).
            ending = self.progress["phase_step"] == total or not self.budget_left(phase)
            evaluation = (
                self.periodic.measure(self.live, phase)
                if self.periodic and self.periodic.due(before, before + seconds, ending)
                else None
            )
            if self.reads_now(ending, evaluation):
                self.check_nonfinite(phase)
            window.add(seconds, parts)
            self.log_metrics(phase, objects, window, parts, ending, evaluation)
            self.render_and_checkpoint(phase)

    def stopped_or_spent(self, phase: str) -> bool:
        """Raises RunStopped when the launcher asks any rank's run to stop (after a checkpoint) and
        StoreFailed when rank 0's store failed; True when any rank's budget for the phase is
        spent."""
        reason = self.report.stop_reason()
        stop, spent, failed = any_rank_each(
            [reason is not None, not self.budget_left(phase), self.report.error is not None],
            self.device,
        )
        if failed:
            self.check_store()
        if stop:
            self.save_checkpoint({"step": self.progress["step"], "phase": phase})
            raise RunStopped(reason or "stopped by the launcher (asked on rank 0)")
        return spent

    def train_step(self, phase: str, objects: PhaseObjects) -> Parts:
        """One data-parallel step at the phase's scheduled lr; a non-finite one is skipped on every
        rank (its `skipped` part is 1). Returns the step's loss parts, on the device: nothing in a
        step waits for the device, the logging steps read what they show (`check_nonfinite`,
        `log_metrics`)."""
        params, optimizer, lr_at = objects
        progress = self.budget.progress(
            phase, self.progress["phase_step"], self.progress["elapsed"]
        )
        ramp = (
            min(1.0, (self.progress["phase_step"] + 1) / self.lr_ramp_steps)
            if self.lr_ramp_steps
            else 1.0
        )
        for group in optimizer.param_groups:
            # a checkpoint saved before groups had scales restores groups without one
            group["lr"] = lr_at(progress) * ramp * group.get("lr_scale", 1.0)
        measure_memory = (self.progress["step"] + 1) % self.cfg.metrics_every == 0
        with SavedTensorBytes() if measure_memory else contextlib.nullcontext() as saved:
            loss, parts = self.forward(phase, progress)
        if saved is not None:
            self.activation_mb = saved.megabytes
        optimizer.zero_grad(set_to_none=True)
        with stage("backward"):
            loss.backward()
        # Decided on the device: the fused Adam leaves every tensor (parameters, moments, step
        # counts) as it was where `found_inf` is set, so the host never waits for the verdict.
        skipped = any_rank_tensor(nonfinite(loss, params))
        self.nonfinite.add(skipped)
        average_gradients(params)
        optimizer.found_inf = skipped  # type: ignore[attr-defined]
        with stage("optimizer"):
            optimizer.step()
        parts["skipped"] = skipped
        self.progress["phase_step"] += 1
        self.progress["step"] += 1
        self.timeline.setdefault("first_step_at", time.time())
        self.progress["steps"][phase] = self.progress["steps"].get(phase, 0) + 1
        return parts

    def forward(self, phase: str, progress: float) -> tuple[torch.Tensor, dict]:
        with stage("ray_batch"):
            rays = self.state.sampler.next()  # on the device (workers/train/ray_batches.py)
        noise = Noise() if self.profile.perturb else None
        step = Step(phase, rays, noise, progress, self.progress["phase_step"], self.cfg.seed)
        with lent(self.state.generator):
            return self.method.step(self.models, step)

    def reads_now(self, ending: bool, evaluation: dict | None) -> bool:
        """Whether this step reads the device (its metrics row, the non-finite streak): a logging
        step, a checkpoint's, the phase's last, and at least every `max_nonfinite_steps`."""
        step, cfg = self.progress["step"], self.cfg
        every = min(cfg.metrics_every, cfg.max_nonfinite_steps)
        return step % every == 0 or step % cfg.checkpoint_every == 0 or ending or bool(evaluation)

    def check_nonfinite(self, phase: str) -> None:
        """Reads the device's count of skipped steps (one host read, on logging steps and at least
        every `max_nonfinite_steps`) and ends the run when a streak reached the limit."""
        worst, current = self.nonfinite.read()
        self.progress["nonfinite"] = current
        if worst >= self.cfg.max_nonfinite_steps:
            raise NonFiniteRun(
                f"{worst} consecutive steps had a non-finite loss or "
                f"gradient ({phase} phase, by step {self.progress['phase_step']}); the run "
                "stops and keeps its last good checkpoint. Lower the learning rate (--set "
                "lr=...) or check the scene's images."
            )

    def log_metrics(
        self,
        phase: str,
        objects: PhaseObjects,
        window: MetricsWindow,
        parts: Parts,
        ending: bool,
        evaluation: dict | None,
    ) -> None:
        """Rank 0 writes a row every `metrics_every` steps, at the phase's end and with every
        evaluation."""
        step = self.progress["step"]
        if self.sink is None or not (step % self.cfg.metrics_every == 0 or ending or evaluation):
            return
        record = {
            **window.row(parts, self.device),
            "phase": phase,
            "phase_step": self.progress["phase_step"],
            "lr": objects.optimizer.param_groups[0]["lr"],
            "activation_memory_mb": self.activation_mb,
            "wall_time_s": sum(self.progress["elapsed"].values()),
            **(evaluation or {}),
        }
        self.sink.write(step, record)
        self.report("write", step, record)

    def render_and_checkpoint(self, phase: str) -> None:
        step = self.progress["step"]
        if self.cfg.val_every and step % self.cfg.val_every == 0 and self.session.rank == 0:
            views = self.scene.splits.get("val", self.scene.train)
            path = write_validation_renders(self.live, phase, views, self.run_dir, step)
            self.report(
                "artifact", "render", path, name=f"renders/{path.name}", phase=phase, step=step
            )
        if step % self.cfg.checkpoint_every == 0:
            self.save_checkpoint({"step": step, "phase": phase})

    def train(self) -> None:
        resumed = self.restore()
        if self.sink is not None:
            if resumed:
                self.sink.resume(self.progress["step"])
            else:
                self.sink.path.write_text("")
        self.report("resume", self.progress["step"])
        if not resumed:
            self.start_phase(self.progress["phase"], fresh=True)
        phases = self.method.phases
        for phase in phases[phases.index(self.progress["phase"]) :]:
            if phase != self.progress["phase"]:
                self.progress.update(phase=phase, phase_step=0)
                self.start_phase(phase, fresh=True)
            self.run_phase(phase)
        self.save_checkpoint({"step": self.progress["step"], "phase": "done"})
        self.check_store()
        write_rank_record(
            self.run_dir,
            self.session.rank,
            {
                **self.timeline,
                "peak_memory_mb": peak_memory_mb(self.device),
                "device": self.device.type,
                "thread": threading.current_thread().name,
            },
        )
        if self.session.rank == 0:
            save_final(self.state, self.cfg, self.run_dir / "final")


def write_rank_record(run_dir: Path, rank: int, record: dict) -> None:
    """workers/rank<r>.json: when this rank started, had its scene and pixels, and ended its first
    step (this attempt's wall clock), and its peak memory (CPU: the process's peak RSS): per-rank
    numbers for benchmarks."""
    workers = Path(run_dir) / "workers"
    workers.mkdir(parents=True, exist_ok=True)
    (workers / f"rank{rank}.json").write_text(json.dumps(record, indent=1))


def write_pid(run_dir: Path, rank: int) -> None:
    workers = Path(run_dir) / "workers"
    workers.mkdir(parents=True, exist_ok=True)
    (workers / f"rank{rank}.pid").write_text(str(os.getpid()))

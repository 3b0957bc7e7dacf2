"""The per-rank training loop: phases, data-parallel steps, non-finite skipping, checkpoints,
metrics.

Every rank draws its disjoint share of the same global ray batch, computes its loss on it, and the
gradients are averaged (plain data parallel). A step whose loss or gradients are non-finite on any
rank is skipped on every rank; too many in a row end the run with a reason (the last good checkpoint
stays)."""

from __future__ import annotations

import contextlib
import json
import os
import resource
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import torch

from model.errors import Failed
from model.methods.base import method_state
from model.methods.schedules import phase_progress
from model.scenes import RaySampler, load_scene
from workers.config import TrainConfig
from workers.memory import SavedTensorBytes
from workers.models import PhaseObjects, build_models, build_optimizer
from workers.pixels import attach_pixel_caches
from workers.store import RunStore, StoreWriteError
from workers.train.distributed import (
    any_rank,
    any_rank_each,
    average_gradients,
    grads_finite,
    is_distributed,
)
from workers.train.periodic_eval import PeriodicEval
from workers.train.session import Session
from workers.train.sinks import JsonlSink
from workers.train.validation import write_validation_renders


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


def peak_memory_mb(device: torch.device) -> float:
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux reports KiB


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
        self.profile = cfg.resolved_profile()
        self.scene = load_scene(scene_dir, downscale=cfg.downscale)
        self.timeline["scene_loaded_at"] = time.time()
        attach_pixel_caches(self.scene)
        self.timeline["pixels_ready_at"] = time.time()
        self.aabb = self.scene.bounds.aabb
        self.method = cfg.method_for_run()
        self.models = build_models(self.method, self.scene.num_images, self.aabb, cfg.seed).to(
            device
        )
        self.method.to(device)
        self.sampler = RaySampler(
            self.scene.train,
            self.aabb,
            cfg.global_batch,
            cfg.seed,
            session.rank,
            session.world_size,
        )
        # Per-rank seeds, on the device the samplers draw on (a CPU generator cannot fill CUDA
        # tensors).
        self.generator = torch.Generator(device=device).manual_seed(cfg.seed * 7919 + session.rank)
        self.progress: dict[str, Any] = {
            "phase": cfg.phases[0],
            "phase_step": 0,
            "step": 0,
            "elapsed": {},
            "steps": {},
            "nonfinite": 0,
        }
        self.phase_objects: PhaseObjects | None = None
        self.activation_mb: float | None = None
        self.sink = JsonlSink(self.run_dir / "metrics.jsonl") if session.rank == 0 else None
        self.store = store if session.rank == 0 else None
        # rank 0's first StoreWriteError; ends the run on every rank
        self.store_error: str | None = None
        # ... and whether another attempt could do better (StoreWriteError.retryable)
        self.store_retryable = False
        self.periodic = PeriodicEval(self) if session.rank == 0 and cfg.eval_every_s else None

    # ----- checkpoints
    # -------------------------------------------------------------------------------
    def _generator_states(self) -> list[torch.Tensor]:
        state = self.generator.get_state()
        if not is_distributed():
            return [state]
        import torch.distributed as dist

        gathered: list[Any] = [None] * self.session.world_size
        dist.all_gather_object(gathered, state)
        return gathered

    def save_checkpoint(self, metrics: dict) -> None:
        generator_states = self._generator_states()  # collective: every rank takes part
        if self.session.rank != 0:
            self.session.report(metrics, None)
            return
        optimizer = self.current_phase().optimizer
        state = {
            "progress": self.progress,
            "models": self.models.state_dict(),
            "method": self.method.state_dict(),
            "optimizer": optimizer.state_dict(),
            "sampler": self.sampler.state_dict(),
            "generators": generator_states,
            "torch_rng": torch.get_rng_state(),
            "config": self.cfg.model_dump(),
            "resolved_profile": self.profile.model_dump(mode="json"),
        }
        with tempfile.TemporaryDirectory() as tmp:
            torch.save(state, Path(tmp) / "state.pt")
            step = self.progress["step"]
            self.to_store(
                "artifact",
                "checkpoint",
                Path(tmp) / "state.pt",
                name=f"checkpoint-step{step:07d}.pt",
                phase=self.progress["phase"],
                step=step,
            )
            self.session.report(metrics, Path(tmp))

    def to_store(self, method: str, *args: object, **kwargs: object) -> None:
        """Rank 0's report to the launcher's store. A write that failed for good (disk full, the
        database gone past its retries) is remembered, not raised: raising on one rank would leave
        the others waiting in a collective. `check_store` ends the run on every rank at the next
        step boundary."""
        if self.store is None or self.store_error is not None:
            return
        try:
            getattr(self.store, method)(*args, **kwargs)
        except StoreWriteError as error:
            self.store_error, self.store_retryable = str(error), error.retryable

    def check_store(self) -> None:
        if any_rank(self.store_error is not None, self.device):
            raise StoreFailed(
                f"the run stopped because its store could not be written: {self.store_error}"
                if self.store_error
                else "rank 0 could not write to the run's store",
                self.store_retryable,
            )

    def restore(self) -> bool:
        with self.session.resume_dir() as path:
            if path is None:
                return False
            # On the CPU: RNG states must stay CPU tensors; load_state_dict copies the rest onto the
            # device.
            state = torch.load(Path(path) / "state.pt", map_location="cpu", weights_only=False)
        self.progress = state["progress"]
        self.models.load_state_dict(state["models"])
        self.method.load_state_dict(method_state(state))
        self.models.to(self.device)
        self.start_phase(self.progress["phase"])
        optimizer = self.current_phase().optimizer
        # the lr follows from progress (phase_progress)
        optimizer.load_state_dict(state["optimizer"])
        self.sampler.load_state_dict(state["sampler"])
        states = state["generators"]
        self.generator.set_state(
            states[self.session.rank] if self.session.rank < len(states) else states[0]
        )
        torch.set_rng_state(state["torch_rng"])
        return True

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
        self.phase_objects = build_optimizer(self.method, self.models, phase)
        self.lr_ramp_steps = self.method.lr_ramp_steps(phase)
        self.to_store("phase_started", phase)

    def budget_left(self, phase: str) -> bool:
        if self.cfg.budget_min is None:
            return True
        budget = self.cfg.budget_min * 60
        spent = sum(self.progress["elapsed"].values())
        share = self.method.budget_share(phase)
        if share is not None:
            return self.progress["elapsed"].get(phase, 0.0) < share * budget
        return spent < budget

    def phase_progress(self, phase: str) -> float:
        """Fraction of the phase done: of its steps, or under a budget of its training-time
        allotment (a phase with a share: that share of the budget; the others: whatever the phases
        before them left), whichever is larger."""
        elapsed = self.progress["elapsed"]
        allotted = None
        if self.cfg.budget_min is not None:
            budget = self.cfg.budget_min * 60
            share = self.method.budget_share(phase)
            before = self.method.phases[: self.method.phases.index(phase)]
            allotted = (
                share * budget
                if share is not None
                else budget - sum(elapsed.get(p, 0.0) for p in before)
            )
        return phase_progress(
            self.progress["phase_step"],
            self.method.phase_steps(phase),
            elapsed.get(phase, 0.0),
            allotted,
        )

    def step_once(self, phase: str, progress: float) -> tuple[torch.Tensor, dict]:
        rays = self.sampler.next().to(self.device)
        generator = self.generator if self.profile.perturb else None
        return self.method.step(
            self.models,
            phase,
            rays,
            generator,
            progress,
            self.progress["phase_step"],
            self.cfg.seed,
        )

    def run_phase(self, phase: str) -> None:
        params, optimizer, lr_at = self.current_phase()
        total = self.method.phase_steps(phase)
        window_seconds, window_steps, samples_in_window = 0.0, 0, 0.0
        while self.progress["phase_step"] < total:
            reason = self.store.stop_reason() if self.store is not None else None
            stop, spent, failed = any_rank_each(
                [reason is not None, not self.budget_left(phase), self.store_error is not None],
                self.device,
            )
            if failed:
                self.check_store()
            if stop:
                self.save_checkpoint({"step": self.progress["step"], "phase": phase})
                raise RunStopped(reason or "stopped by the launcher (asked on rank 0)")
            if spent:
                break
            t0 = time.perf_counter()
            progress = self.phase_progress(phase)
            ramp = (
                min(1.0, (self.progress["phase_step"] + 1) / self.lr_ramp_steps)
                if self.lr_ramp_steps
                else 1.0
            )
            for group in optimizer.param_groups:
                group["lr"] = lr_at(progress) * ramp
            measure_memory = (self.progress["step"] + 1) % self.cfg.metrics_every == 0
            with SavedTensorBytes() if measure_memory else contextlib.nullcontext() as saved:
                loss, parts = self.step_once(phase, progress)
            if saved is not None:
                self.activation_mb = saved.megabytes
            optimizer.zero_grad(set_to_none=True)
            finite = bool(torch.isfinite(loss))
            if finite:
                loss.backward()
                finite = grads_finite(params)
            if any_rank(not finite, self.device):
                self.progress["nonfinite"] += 1
                if self.progress["nonfinite"] >= self.cfg.max_nonfinite_steps:
                    raise NonFiniteRun(
                        f"{self.progress['nonfinite']} consecutive steps had a non-finite loss or "
                        f"gradient ({phase} phase, step {self.progress['phase_step']}); the run "
                        "stops and keeps its last good checkpoint. Lower the learning rate (--set "
                        "lr=...) or check the scene's images."
                    )
                optimizer.zero_grad(set_to_none=True)
                parts["skipped"] = 1.0
            else:
                self.progress["nonfinite"] = 0
                average_gradients(params)
                optimizer.step()
            self.progress["phase_step"] += 1
            self.progress["step"] += 1
            self.timeline.setdefault("first_step_at", time.time())
            self.progress["steps"][phase] = self.progress["steps"].get(phase, 0) + 1
            # compute only: checkpoints and renders are not training time
            seconds = time.perf_counter() - t0
            before = sum(self.progress["elapsed"].values())
            self.progress["elapsed"][phase] = self.progress["elapsed"].get(phase, 0.0) + seconds
            # Rank 0's own view of the end is exact: any rank's spent budget stops every rank
            # (any_rank_each).
            ending = self.progress["phase_step"] == total or not self.budget_left(phase)
            evaluation = (
                self.periodic.measure(self, phase)
                if self.periodic and self.periodic.due(before, before + seconds, ending)
                else None
            )
            window_seconds += seconds
            window_steps += 1
            samples_in_window += parts.get("samples_per_ray", 0.0)
            step = self.progress["step"]
            if self.sink is not None and (
                step % self.cfg.metrics_every == 0 or ending or evaluation
            ):
                rays = self.cfg.global_batch * window_steps / window_seconds
                record = {
                    **parts,
                    "phase": phase,
                    "phase_step": self.progress["phase_step"],
                    "lr": optimizer.param_groups[0]["lr"],
                    "rays_per_s": rays,
                    "samples_per_s": rays * samples_in_window / window_steps,
                    "peak_memory_mb": peak_memory_mb(self.device),
                    "activation_memory_mb": self.activation_mb,
                    "wall_time_s": sum(self.progress["elapsed"].values()),
                    **(evaluation or {}),
                }
                self.sink.write(step, record)
                self.to_store("write", step, record)
                window_seconds, window_steps, samples_in_window = 0.0, 0, 0.0
            if self.cfg.val_every and step % self.cfg.val_every == 0 and self.session.rank == 0:
                path = write_validation_renders(self, step)
                self.to_store(
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
        self.to_store("resume", self.progress["step"])
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
            self.save_final()

    def save_final(self) -> None:
        final = self.run_dir / "final"
        final.mkdir(parents=True, exist_ok=True)
        torch.save(
            {
                "models": self.models.state_dict(),
                "method": self.method.state_dict(),
                "progress": self.progress,
                "config": self.cfg.model_dump(),
                "resolved_profile": self.profile.model_dump(mode="json"),
            },
            final / "models.pt",
        )
        self.method.save_final(final)
        (final / "progress.json").write_text(json.dumps(self.progress, indent=1))


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

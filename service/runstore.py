"""The service's side of workers.store.RunStore: a run's metrics go to the database (one row per
(job, phase, metric, step), upserted), its files to the artifact store, and every step boundary asks
the database whether the job was cancelled or its lease passed to another attempt.

Fencing: every write carries the run's attempt and passes queue.hold inside its own transaction, so
a write from an attempt that lost the job is refused (StaleAttempt) and stores nothing, and each row
records the attempt that wrote it. While the database is unavailable, writes wait and retry
(service.db.retrying, for Settings.retry_s) and the stop check lets the run go on; past that budget
a write raises DatabaseUnavailable, and a run that has not reached the database for as long stops on
its own: both happen before the lease can lapse (Settings.check_lease_and_retry), so no second
attempt trains beside it.

It holds only strings and numbers, so Ray pickles it to the workers; each process opens its own
engine."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

from sqlalchemy import delete, select, update
from sqlalchemy.dialects import postgresql, sqlite

from service import queue
from service.db import UNAVAILABLE, reading, retrying, transaction
from service.store import ArtifactStore
from service.tables import Job, JobPhase, Metric

STOP_CHECK_S = 1.0  # how often a step boundary really asks the database


@dataclass
class DatabaseRunStore:
    db_url: str
    artifact_root: str
    job_id: int
    attempt: int
    retry_s: float
    keep_checkpoints: int = 2
    _checked_at: float = field(default=0.0, repr=False)
    # the last time the stop check got an answer
    _reached_at: float | None = field(default=None, repr=False)
    _reason: str | None = field(default=None, repr=False)

    @property
    def artifacts(self) -> ArtifactStore:
        return ArtifactStore(self.db_url, Path(self.artifact_root))

    def resume(self, step: int) -> None:
        def forget() -> None:
            with transaction(self.db_url) as session:
                queue.hold(session, self.job_id, self.attempt)
                session.execute(
                    delete(Metric).where(Metric.job_id == self.job_id, Metric.step > step)
                )

        retrying(f"forgetting job {self.job_id}'s metrics after step {step}", forget, self.retry_s)

    def write(self, step: int, metrics: dict) -> None:
        retrying(
            f"writing job {self.job_id}'s metrics of step {step}",
            lambda: self._write(step, metrics),
            self.retry_s,
        )

    def _write(self, step: int, metrics: dict) -> None:
        phase = str(metrics.get("phase", "main"))
        wall = metrics.get("wall_time_s")
        rows = [
            {
                "job_id": self.job_id,
                "phase": phase,
                "name": name,
                "step": step,
                "value": float(value),
                "wall_time_s": wall,
                "attempt": self.attempt,
            }
            for name, value in metrics.items()
            if isinstance(value, (int, float))
            and not isinstance(value, bool)
            and math.isfinite(value)
        ]
        with transaction(self.db_url) as session:
            queue.hold(session, self.job_id, self.attempt)
            if rows:
                dialect = postgresql if session.get_bind().dialect.name == "postgresql" else sqlite
                insert = dialect.insert(Metric).values(rows)
                session.execute(
                    insert.on_conflict_do_update(
                        index_elements=["job_id", "phase", "name", "step"],
                        set_={
                            "value": insert.excluded.value,
                            "wall_time_s": insert.excluded.wall_time_s,
                            "attempt": insert.excluded.attempt,
                        },
                    )
                )
            # Progress for `GET /v1/jobs/{id}`, only while the job runs (not once it was handed
            # back).
            progress = {"phase": phase, "step": step}
            if metrics.get("rays_per_s") is not None:
                progress["rays_per_s"] = metrics["rays_per_s"]
            session.execute(
                update(Job)
                .where(Job.id == self.job_id, Job.attempts == self.attempt, Job.state == "running")
                .values(**progress),
                execution_options={"synchronize_session": False},
            )
            if "phase_step" in metrics:
                session.execute(
                    update(JobPhase)
                    .where(JobPhase.job_id == self.job_id, JobPhase.name == phase)
                    .values(step=int(metrics["phase_step"])),
                    execution_options={"synchronize_session": False},
                )

    def artifact(
        self, kind: str, path: Path, *, name: str, phase: str | None, step: int | None
    ) -> None:
        store = self.artifacts
        retrying(
            f"storing job {self.job_id}'s {name}",
            lambda: store.put(
                self.job_id, kind, name, Path(path), phase=phase, step=step, attempt=self.attempt
            ),
            self.retry_s,
        )
        if kind == "checkpoint":
            retrying(
                f"pruning job {self.job_id}'s checkpoints",
                lambda: store.prune(self.job_id, "checkpoint", self.keep_checkpoints, self.attempt),
                self.retry_s,
            )

    def phase_started(self, phase: str) -> None:
        retrying(
            f"starting job {self.job_id}'s {phase} phase",
            lambda: queue.phase_started(self.db_url, self.job_id, self.attempt, phase),
            self.retry_s,
        )

    def stop_reason(self) -> str | None:
        now = time.monotonic()
        if self._reason is None and now - self._checked_at >= STOP_CHECK_S:
            self._checked_at = now
            self._reached_at = self._reached_at or now
            try:
                with reading(self.db_url) as session:
                    row = session.execute(
                        select(Job.state, Job.attempts, Job.cancel_requested).where(
                            Job.id == self.job_id
                        )
                    ).first()
            except UNAVAILABLE:
                if now - self._reached_at < self.retry_s:
                    # the database is away: train on; the next write waits for it (retrying)
                    return None
                self._reason = (
                    f"the database has not answered for {now - self._reached_at:.0f} s "
                    f"(LECO_DB_RETRY_S is {self.retry_s:g} s): attempt {self.attempt} stops before "
                    "its lease can pass to another attempt; the job resumes from its last stored "
                    "checkpoint"
                )
                return self._reason
            self._reached_at = now
            if row is None:
                self._reason = f"job {self.job_id} was deleted"
            elif row.cancel_requested:
                self._reason = "cancelled by the user"
            elif row.state == "queued" and row.attempts == self.attempt:
                self._reason = (
                    f"job {self.job_id} was returned to the queue (its dispatcher stopped or its "
                    "lease expired): it resumes from this checkpoint on its next claim"
                )
            elif row.state != "running" or row.attempts != self.attempt:
                self._reason = (
                    f"attempt {self.attempt} no longer holds job {self.job_id} (state {row.state}, "
                    f"attempt {row.attempts}): its lease expired"
                )
        return self._reason

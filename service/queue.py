"""The durable job queue. The database is the source of truth: every state change is one conditional
UPDATE on the state (and attempt) it expects, so two dispatchers, a cancel request and a lease
reaper can race without ever handing one job to two owners or moving a finished job.

    queued -> running -> succeeded | failed | cancelled        queued -> cancelled
    running -> queued  (lease expired, attempts left: resumes from its last checkpoint)
"""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import cast

from sqlalchemy import ColumnElement, CursorResult, Result, and_, or_, select, update
from sqlalchemy.orm import Session

from service.db import transaction
from service.tables import TERMINAL, Job, JobPhase, Scene, utcnow
from workers.store import StoreWriteError


class StaleAttempt(StoreWriteError):
    """A write from an attempt that no longer holds its job (a later attempt claimed it, or it was
    deleted): refused, nothing of it stored. The run stops; the attempt that holds the job goes
    on."""

    retryable = True


def hold(session: Session, job_id: int, attempt: int) -> None:
    """The fence every write of a run passes inside its own transaction: the job's row is locked
    (FOR UPDATE on PostgreSQL; SQLite's BEGIN IMMEDIATE already serialises writers) and must still
    be at `attempt`, so a claim cannot slip in between this check and the write's commit. Raises
    StaleAttempt otherwise."""
    attempts = session.scalar(select(Job.attempts).where(Job.id == job_id).with_for_update())
    if attempts is None:
        raise StaleAttempt(f"job {job_id} was deleted: attempt {attempt}'s write was refused")
    if attempts != attempt:
        raise StaleAttempt(
            f"attempt {attempt} no longer holds job {job_id} (attempt {attempts} does): its write "
            "was refused"
        )


def _rowcount(result: Result) -> int:
    # Session.execute is typed to return a plain Result, since it cannot promise a cursor for every
    # statement (sqlalchemy/sqlalchemy#12913); for the UPDATEs without RETURNING here it is a
    # CursorResult.
    return cast(CursorResult, result).rowcount


def enqueue(
    session: Session,
    kind: str,
    scene_id: int,
    method: str,
    profile: str,
    config: dict,
    phases: list[tuple[str, int]],
    parent_id: int | None = None,
) -> Job:
    """A new queued job and its phases ((name, steps) in order); service/jobs/submit.py makes the
    arguments from a job kind and its config."""
    job = Job(
        kind=kind,
        parent_id=parent_id,
        scene_id=scene_id,
        state="queued",
        method=method,
        profile=profile,
        config=config,
        total_steps=sum(steps for _, steps in phases),
        step=0,
        attempts=0,
        cancel_requested=False,
        submitted_at=utcnow(),
    )
    session.add(job)
    session.flush()
    for position, (phase, steps) in enumerate(phases):
        session.add(
            JobPhase(
                job_id=job.id,
                name=phase,
                position=position,
                state="queued",
                steps_total=steps,
                step=0,
            )
        )
    return job


def runnable_on_its_scene(runs_on: dict[str, tuple[str, ...]]) -> ColumnElement[bool]:
    """A job's scene is in a state its kind runs on (`runs_on`: kind -> scene states, from the
    job-kind registry); any other kind (none given, or no longer registered) runs on a ready scene,
    and one no longer registered fails there naming its kind."""
    return or_(
        and_(Job.kind.not_in(list(runs_on)), Scene.state == "ready"),
        *(and_(Job.kind == kind, Scene.state.in_(states)) for kind, states in runs_on.items()),
    )


def claim(
    db_url: str, owner: str, lease_s: float, runs_on: dict[str, tuple[str, ...]] | None = None
) -> tuple[int, int] | None:
    """Takes the oldest queued job whose scene is in a state its kind runs on (`runs_on`; ready
    by default, a poses job the scene it poses): (job id, attempt), or None.

    One statement: on PostgreSQL the subquery locks the row with FOR UPDATE SKIP LOCKED, so
    concurrent claimers skip each other's rows; on SQLite (which drops FOR UPDATE) the single UPDATE
    ... RETURNING inside a BEGIN IMMEDIATE transaction is atomic on its own."""
    now = utcnow()
    candidate = (
        select(Job.id)
        .join(Scene, Scene.id == Job.scene_id)
        .where(Job.state == "queued", runnable_on_its_scene(runs_on or {}))
        .order_by(Job.id)
        .limit(1)
        .with_for_update(skip_locked=True, of=Job)
        .scalar_subquery()
    )
    statement = (
        update(Job)
        .where(Job.id == candidate, Job.state == "queued")
        .values(
            state="running",
            attempts=Job.attempts + 1,
            lease_owner=owner,
            lease_expires_at=now + timedelta(seconds=lease_s),
            started_at=now,
        )
        .returning(Job.id, Job.attempts)
    )
    with transaction(db_url) as session:
        row = session.execute(statement, execution_options={"synchronize_session": False}).first()
    return (row[0], row[1]) if row else None


def heartbeat(db_url: str, job_id: int, attempt: int, owner: str, lease_s: float) -> bool:
    """Renews the lease; False when this owner no longer holds the job (expired and re-claimed,
    finished)."""
    with transaction(db_url) as session:
        result = session.execute(
            update(Job)
            .where(
                Job.id == job_id,
                Job.state == "running",
                Job.attempts == attempt,
                Job.lease_owner == owner,
            )
            .values(lease_expires_at=utcnow() + timedelta(seconds=lease_s)),
            execution_options={"synchronize_session": False},
        )
    return _rowcount(result) == 1


def finish(db_url: str, job_id: int, attempt: int, state: str, error: str | None = None) -> bool:
    """running -> a terminal state, only for the attempt that holds the job. Phases that were not
    finished take the job's state (a succeeded job's phases all succeeded)."""
    assert state in TERMINAL
    now = utcnow()
    with transaction(db_url) as session:
        result = session.execute(
            update(Job)
            .where(Job.id == job_id, Job.state == "running", Job.attempts == attempt)
            .values(
                state=state, error=error, finished_at=now, lease_owner=None, lease_expires_at=None
            ),
            execution_options={"synchronize_session": False},
        )
        if _rowcount(result) != 1:
            return False
        close_phases(session, job_id, state, now)
    return True


def close_phases(session: Session, job_id: int, state: str, now: datetime) -> None:
    session.execute(
        update(JobPhase)
        .where(JobPhase.job_id == job_id, JobPhase.state.in_(("queued", "running")))
        .values(state=state, finished_at=now),
        execution_options={"synchronize_session": False},
    )


def requeue_expired(db_url: str, max_attempts: int) -> list[tuple[int, str]]:
    """Jobs whose lease ran out (their dispatcher or worker died): back to the queue while attempts
    are left, else failed; cancelled if a cancel was asked for. Returns (job id, new state)
    pairs."""
    now = utcnow()
    moved = []
    with transaction(db_url) as session:
        expired = session.execute(
            select(Job.id, Job.attempts, Job.cancel_requested, Job.lease_owner)
            .where(Job.state == "running", Job.lease_expires_at < now)
            .with_for_update(skip_locked=True)
        ).all()
        for job_id, attempts, cancel, owner in expired:
            reason = (
                f"lease of attempt {attempts} expired at {now:%Y-%m-%d %H:%M:%S} UTC (owner "
                f"{owner} stopped renewing it)"
            )
            if cancel:
                state, error = "cancelled", None
            elif attempts >= max_attempts:
                state, error = (
                    "failed",
                    f"{reason}; no attempts left ({attempts} of {max_attempts})",
                )
            else:
                state, error = "queued", reason
            values: dict[str, object] = dict(
                state=state, error=error, lease_owner=None, lease_expires_at=None
            )
            if state != "queued":
                values["finished_at"] = now
            result = session.execute(
                update(Job)
                .where(Job.id == job_id, Job.state == "running", Job.attempts == attempts)
                .values(**values),
                execution_options={"synchronize_session": False},
            )
            if _rowcount(result) != 1:
                continue
            if state == "queued":
                requeue_phases(session, job_id)
            else:
                close_phases(session, job_id, state, now)
            moved.append((job_id, state))
    return moved


def release(db_url: str, job_id: int, attempt: int, reason: str) -> bool:
    """running -> queued for the attempt that holds the job (not asked to cancel): its dispatcher is
    shutting down. The run sees it at its next step boundary, checkpoints and stops; the next claim
    resumes from there. False when this attempt no longer holds the job."""
    with transaction(db_url) as session:
        result = session.execute(
            update(Job)
            .where(
                Job.id == job_id,
                Job.state == "running",
                Job.attempts == attempt,
                Job.cancel_requested.is_(False),
            )
            .values(state="queued", error=reason, lease_owner=None, lease_expires_at=None),
            execution_options={"synchronize_session": False},
        )
        if _rowcount(result) != 1:
            return False
        requeue_phases(session, job_id)
    return True


def requeue_phases(session: Session, job_id: int) -> None:
    session.execute(
        update(JobPhase)
        .where(JobPhase.job_id == job_id, JobPhase.state == "running")
        .values(state="queued"),
        execution_options={"synchronize_session": False},
    )


def cancel(db_url: str, job_id: int) -> str | None:
    """A queued job is cancelled at once; a running one is asked to stop at its next step boundary.
    Returns the job's state afterwards ('cancelled', 'running' with the request recorded, or the
    terminal state it already had), or None when there is no such job."""
    now = utcnow()
    with transaction(db_url) as session:
        result = session.execute(
            update(Job)
            .where(Job.id == job_id, Job.state == "queued")
            .values(state="cancelled", finished_at=now, cancel_requested=True),
            execution_options={"synchronize_session": False},
        )
        if _rowcount(result) == 1:
            close_phases(session, job_id, "cancelled", now)
            return "cancelled"
        session.execute(
            update(Job)
            .where(Job.id == job_id, Job.state == "running")
            .values(cancel_requested=True),
            execution_options={"synchronize_session": False},
        )
        return session.scalar(select(Job.state).where(Job.id == job_id))


def phase_started(db_url: str, job_id: int, attempt: int, phase: str) -> None:
    """Marks `phase` running and every phase before it succeeded (for the attempt that holds the
    job)."""
    now = utcnow()
    with transaction(db_url) as session:
        hold(session, job_id, attempt)
        if session.scalar(select(Job.state).where(Job.id == job_id)) != "running":
            return
        phases = session.scalars(
            select(JobPhase).where(JobPhase.job_id == job_id).order_by(JobPhase.position)
        ).all()
        current = next((p.position for p in phases if p.name == phase), None)
        for p in phases:
            if current is not None and p.position < current and p.state != "succeeded":
                p.state, p.finished_at = "succeeded", now
            elif p.name == phase and p.state != "running":
                p.state, p.started_at = "running", p.started_at or now
        job = session.get(Job, job_id)
        if job is None:  # not after hold() found and locked the row; checked so the type says so
            raise StaleAttempt(f"job {job_id} was deleted: attempt {attempt}'s write was refused")
        job.phase = phase

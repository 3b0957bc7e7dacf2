"""One claimed attempt of a job of any kind, run to its end: the kind's work (kinds.py) does the
job's own part; this module owns what every kind shares, the attempt's outcome under the queue's
lease and fence.

    the work returns -> succeeded (if this attempt still holds the job) the work stops on request ->
    cancelled when a cancel was asked for, else lost (the lease passed on) another attempt holds the
    job, or the database stayed away -> handed back to the queue (a later attempt resumes), lost
    anything else -> failed, with the reason

The embedded dispatcher calls `execute` in its own process; on a cluster a Ray job runs `python -m
service.execute`, which calls the same."""

from __future__ import annotations

import logging

from sqlalchemy import select

from service import queue
from service.db import DatabaseUnavailable, reading, retrying
from service.jobs.context import Attempt, job_cancelled
from service.jobs.kinds import get_kind
from service.queue import StaleAttempt
from service.runstore import DatabaseRunStore
from service.settings import Settings
from service.tables import Job, Scene
from workers.store import RunError, RunGaveUp, StopRequested

log = logging.getLogger("leco.execute")


def finish(settings: Settings, job_id: int, attempt: int, state: str, error: str | None) -> bool:
    # A job's end must not be lost to a database restart: wait for it (the lease covers the wait).
    return retrying(
        f"recording job {job_id} as {state}",
        lambda: queue.finish(settings.db_url, job_id, attempt, state, error),
        settings.retry_s,
    )


def reason_of(error: Exception) -> str:
    """A RunError already says what a user can act on; anything else is named by its type."""
    return str(error) if isinstance(error, RunError) else f"{type(error).__name__}: {error}"


def execute(settings: Settings, job_id: int, attempt: int) -> str:
    """Returns the state it left the job in, or 'lost' when this attempt no longer holds it."""
    url = settings.db_url
    with reading(url) as session:
        job = session.get(Job, job_id)
        scene_path = (
            session.scalar(select(Scene.path).where(Scene.id == job.scene_id)) if job else None
        )
    if job is None or job.state != "running" or job.attempts != attempt:
        return "lost"
    store = DatabaseRunStore(
        url, str(settings.artifacts), job_id, attempt, settings.retry_s, settings.keep_checkpoints
    )
    try:
        # the scenes foreign key forbids it; should it happen, the job fails saying so
        if scene_path is None:
            raise RunError(f"scene {job.scene_id} of job {job_id} no longer exists")
        get_kind(job.kind).load_work()(Attempt(settings, job, attempt, scene_path, store))
    except StopRequested as stopped:
        if job_cancelled(settings, job_id):
            return "cancelled" if finish(settings, job_id, attempt, "cancelled", None) else "lost"
        log.info("job %s attempt %s stopped: %s", job_id, attempt, stopped)
        return "lost"
    except (RunGaveUp, StaleAttempt, DatabaseUnavailable) as error:
        # Not the job's failure: another attempt holds it, or the database stayed away. Hand the job
        # back to the queue (it resumes from its last stored checkpoint); if the database is still
        # away, the lease lapses and the reaper does the same.
        log.warning("job %s attempt %s gave the job up: %s", job_id, attempt, error)
        try:
            reason = f"attempt {attempt} gave up: {error}"
            retrying(
                f"handing job {job_id} back to the queue",
                lambda: queue.release(url, job_id, attempt, reason),
                settings.retry_s,
            )
        except DatabaseUnavailable:
            pass
        return "lost"
    except Exception as error:  # the job fails with the reason; the service goes on
        log.exception("job %s attempt %s failed", job_id, attempt)
        try:
            return (
                "failed"
                if finish(settings, job_id, attempt, "failed", reason_of(error))
                else "lost"
            )
        except DatabaseUnavailable:
            return "lost"
    try:
        return "succeeded" if finish(settings, job_id, attempt, "succeeded", None) else "lost"
    # the lease lapses; the next attempt finds the work done and stores it
    except DatabaseUnavailable:
        return "lost"

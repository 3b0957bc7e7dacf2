"""What a kind's work gets from the attempt runner (service/jobs/attempt.py): the claimed job, its
scene's folder and the store its writes go through. Its own module so the job-kind table
(kinds.py) can name it without importing the runner that reads the table."""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import select

from service.db import reading, retrying
from service.runstore import DatabaseRunStore
from service.settings import Settings
from service.tables import Job


@dataclass
class Attempt:
    """What a kind's work gets: the job as claimed, its scene's folder, and the store its writes go
    through (fenced by the attempt)."""

    settings: Settings
    job: Job
    number: int
    scene_path: str
    store: DatabaseRunStore

    def cancelled(self) -> bool:
        return job_cancelled(self.settings, self.job.id)


def job_cancelled(settings: Settings, job_id: int) -> bool:
    def read() -> bool:
        with reading(settings.db_url) as session:
            return bool(session.scalar(select(Job.cancel_requested).where(Job.id == job_id)))

    return retrying(f"reading job {job_id}", read, settings.retry_s)

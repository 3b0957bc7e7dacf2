"""Where a job's attempts work on disk (under the service's runs folder)."""

from __future__ import annotations

from pathlib import Path

from service.settings import Settings


def job_dir_for(settings: Settings, job_id: int) -> Path:
    return settings.runs_dir / f"job-{job_id}"


def run_dir_for(settings: Settings, job_id: int, attempt: int) -> Path:
    """Each attempt works in a folder of its own: an attempt that lost its lease but still runs
    cannot write into the folder its successor resumes in."""
    return job_dir_for(settings, job_id) / f"attempt-{attempt}"

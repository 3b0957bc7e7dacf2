"""The finished training job a render, export or view is made of: its stored final networks, checked
and loaded (workers/trained.py)."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import TYPE_CHECKING

from sqlalchemy import select

from service.db import reading, retrying
from service.jobs.paths import run_dir_for
from service.settings import Settings
from service.store import ArtifactStore, describe
from service.tables import Artifact

if TYPE_CHECKING:
    from service.jobs.context import Attempt
    from workers.trained import Trained

FINAL_NAMES = ("final/models.pt", "final/occupancy.pt")  # what a render needs of its training job


def final_files(settings: Settings, parent_id: int, folder: Path) -> Path:
    """The training job's stored final networks, checked against their sha256, copied into
    `folder`/final."""

    def rows() -> list[dict]:
        with reading(settings.db_url) as session:
            found = session.scalars(
                select(Artifact).where(Artifact.job_id == parent_id, Artifact.name.in_(FINAL_NAMES))
            ).all()
            return [describe(r) for r in found]

    store, final = ArtifactStore(settings.db_url, settings.artifacts), folder / "final"
    final.mkdir(parents=True, exist_ok=True)
    for meta in retrying(f"finding job {parent_id}'s final networks", rows, settings.retry_s):
        shutil.copyfile(store.verified_path(meta), folder / meta["name"])
    if not (final / "models.pt").is_file():
        raise FileNotFoundError(f"job {parent_id} has no stored final networks (final/models.pt)")
    return final


def load_parent(settings: Settings, parent_id: int, scene_path: str, folder: Path) -> Trained:
    from workers.trained import load_trained  # PyTorch: in the process that renders, not the API's

    return load_trained(final_files(settings, parent_id, folder), scene_path)


def parent_of(attempt: Attempt) -> tuple[Path, Trained]:
    """A fresh folder for an attempt of a job made of a training job, and that training job's
    networks."""
    job = attempt.job
    folder = run_dir_for(attempt.settings, job.id, attempt.number)
    shutil.rmtree(folder, ignore_errors=True)
    if job.parent_id is None:
        raise ValueError(f"job {job.id} is a {job.kind} job without the training job it is made of")
    return folder, load_parent(attempt.settings, job.parent_id, attempt.scene_path, folder)

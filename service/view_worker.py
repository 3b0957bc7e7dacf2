"""The process side of `POST /v1/jobs/{id}/view`: one camera of a finished training job rendered to
PNG (workers/render/view.py) in a process of the view pool, never in the API process. Each process
keeps the networks of the last few jobs it rendered loaded, so the viewer's next frame costs a
render, not a load."""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path
from typing import TYPE_CHECKING

from sqlalchemy import select

from service.db import reading
from service.jobs.parent import load_parent
from service.settings import Settings
from service.tables import Job, Scene
from workers.render.schemas import ViewRequest

if TYPE_CHECKING:
    from workers.trained import Trained

LOADED_JOBS = 2
_loaded: OrderedDict[int, Trained] = OrderedDict()


def trained_job(settings: Settings, job_id: int) -> Trained:
    if job_id in _loaded:
        _loaded.move_to_end(job_id)
        return _loaded[job_id]
    with reading(settings.db_url) as session:
        job = session.get(Job, job_id)
        scene_path = (
            session.scalar(select(Scene.path).where(Scene.id == job.scene_id)) if job else None
        )
    if job is None or scene_path is None:
        raise FileNotFoundError(f"job {job_id} or its scene no longer exists")
    trained = load_parent(
        settings, job_id, scene_path, Path(settings.data_dir) / "views" / f"job-{job_id}"
    )
    _loaded[job_id] = trained
    while len(_loaded) > LOADED_JOBS:
        _loaded.popitem(last=False)
    return trained


def render_view(settings: Settings, job_id: int, body: dict) -> tuple[bytes, float]:
    """(PNG bytes, seconds the render took) of the camera in `body` (a
    workers.render.schemas.ViewRequest)."""
    from workers.render.view import render_view_png  # PyTorch: loaded in the view pool's process

    return render_view_png(trained_job(settings, job_id), ViewRequest.model_validate(body))

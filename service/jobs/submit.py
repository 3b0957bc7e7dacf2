"""A new job of any kind, queued: its phases and labels from its kind (kinds.py) and config."""

from __future__ import annotations

from pydantic import BaseModel
from sqlalchemy.orm import Session

from service import queue
from service.jobs.kinds import JobKind, Parent
from service.tables import Job


def submit(
    session: Session,
    kind: JobKind,
    scene_id: int,
    cfg: BaseModel,
    parent: Job | None = None,
    parent_info: Parent | None = None,
) -> Job:
    """A job on a scene (`parent` None: it carries its own method and profile, as training does), or
    made of the finished training job `parent` (it inherits that job's scene, method and
    profile)."""
    phases, config = kind.phases(cfg, parent_info), cfg.model_dump(mode="json")
    if parent is None:
        method, profile = kind.labels(cfg)
        return queue.enqueue(session, kind.name, scene_id, method, profile, config, phases)
    return queue.enqueue(
        session,
        kind.name,
        parent.scene_id,
        parent.method,
        parent.profile,
        config,
        phases,
        parent_id=parent.id,
    )

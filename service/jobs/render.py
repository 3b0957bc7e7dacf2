"""A render job's work: a video of its finished training job along a camera path
(workers/render/job.py), its files stored by name at the end, so a retried attempt replaces them."""

from __future__ import annotations

import logging

from service.jobs.context import Attempt
from service.jobs.parent import parent_of
from workers.render.job import outputs, render_video
from workers.render.schemas import RENDER_PHASE, RenderConfig

log = logging.getLogger("leco.render")


def render(attempt: Attempt) -> None:
    job, store = attempt.job, attempt.store
    folder, trained = parent_of(attempt)
    cfg = RenderConfig.model_validate(job.config)
    summary = render_video(
        trained, cfg, folder / "video.mp4", store, log=lambda text: log.debug(text)
    )
    files = outputs(folder / "video.mp4")
    stored = [
        ("render", files["video"]),
        ("render", files["poster"]),
        ("report", files["path"]),
        ("report", files["summary"]),
    ] + ([("render", files["depth"])] if cfg.depth_video else [])
    for kind, path in stored:
        store.artifact(kind, path, name=path.name, phase=RENDER_PHASE, step=summary["frames"])

"""A render job's work: a video of its finished training job along a camera path (workers/render_job.py),
its files stored by name at the end, so a retried attempt replaces them."""

from __future__ import annotations

import logging
import shutil

from service.jobs.attempt import Attempt
from service.jobs.parent import load_parent
from service.jobs.paths import run_dir_for
from workers.render_config import RENDER_PHASE, RenderConfig
from workers.render_job import outputs, render_video

log = logging.getLogger("leco.render")


def render(attempt: Attempt) -> None:
    job, store = attempt.job, attempt.store
    folder = run_dir_for(attempt.settings, job.id, attempt.number)
    shutil.rmtree(folder, ignore_errors=True)
    assert job.parent_id is not None
    trained = load_parent(attempt.settings, job.parent_id, attempt.scene_path, folder)
    cfg = RenderConfig.model_validate(job.config)
    summary = render_video(trained, cfg, folder / "video.mp4", store, log=lambda text: log.debug(text))
    files = outputs(folder / "video.mp4")
    stored = [("render", files["video"]), ("render", files["poster"]), ("report", files["path"]),
              ("report", files["summary"])] + ([("render", files["depth"])] if cfg.depth_video else [])
    for kind, path in stored:
        store.artifact(kind, path, name=path.name, phase=RENDER_PHASE, step=summary["frames"])

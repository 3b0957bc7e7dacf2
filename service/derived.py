"""Render and export jobs: work on a finished training job, queued, claimed, leased, fenced and
retried exactly like training (service/queue.py), run by the same dispatchers. An attempt loads the training
job's stored final networks, renders or exports into a folder of its own, and stores its files only at the
end, by name: a retried attempt replaces them, never adds a second copy."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

from pydantic import BaseModel
from sqlalchemy import select

from service import queue
from service.db import DatabaseUnavailable, reading, retrying
from service.queue import StaleAttempt
from service.runstore import DatabaseRunStore
from service.settings import Settings
from service.store import ArtifactStore, describe
from service.tables import Artifact, Job
from workers.export import FILES, TRANSFORM, export
from workers.render_config import ExportConfig, RenderConfig
from workers.render_job import PHASE as RENDER_PHASE
from workers.render_job import outputs, render_video
from workers.store import StopRequested
from workers.trained import Trained, load_trained

log = logging.getLogger("leco.derived")

EXPORT_PHASE = "export"
FINAL_NAMES = ("final/models.pt", "final/occupancy.pt")  # what a render needs of its training job


def config_of(job: Job) -> RenderConfig | ExportConfig:
    return (RenderConfig if job.kind == "render" else ExportConfig).model_validate(job.config)


def steps_of(cfg: BaseModel, views: int) -> tuple[str, int]:
    """(phase, steps) of a render (a step a frame) or an export (a step a view of a point cloud, else one)."""
    if isinstance(cfg, RenderConfig):
        return RENDER_PHASE, cfg.frame_count
    assert isinstance(cfg, ExportConfig)
    return EXPORT_PHASE, views if cfg.what == "pointcloud" else 1


def rays_per_step(job: Job) -> int | None:
    """Rays one step of a render renders (its ETA); None where steps differ (exports)."""
    if job.kind != "render":
        return None
    return int(job.config["width"]) * int(job.config["height"])


def final_files(settings: Settings, parent_id: int, folder: Path) -> Path:
    """The training job's stored final networks, checked against their sha256, copied into `folder`/final."""
    def rows() -> list[dict]:
        with reading(settings.db_url) as session:
            found = session.scalars(select(Artifact).where(Artifact.job_id == parent_id,
                                                           Artifact.name.in_(FINAL_NAMES))).all()
            return [describe(r) for r in found]

    store, final = ArtifactStore(settings.db_url, settings.artifacts), folder / "final"
    final.mkdir(parents=True, exist_ok=True)
    for meta in retrying(f"finding job {parent_id}'s final networks", rows, settings.retry_s):
        shutil.copyfile(store.verified_path(meta), folder / meta["name"])
    if not (final / "models.pt").is_file():
        raise FileNotFoundError(f"job {parent_id} has no stored final networks (final/models.pt)")
    return final


def load_parent(settings: Settings, parent_id: int, scene_path: str, folder: Path) -> Trained:
    return load_trained(final_files(settings, parent_id, folder), scene_path)


def run(settings: Settings, job: Job, attempt: int, scene_path: str, store: DatabaseRunStore) -> None:
    from service.execute import run_dir_for

    folder = run_dir_for(settings, job.id, attempt)
    shutil.rmtree(folder, ignore_errors=True)
    assert job.parent_id is not None
    trained = load_parent(settings, job.parent_id, scene_path, folder)
    cfg = config_of(job)
    if isinstance(cfg, RenderConfig):
        summary = render_video(trained, cfg, folder / "video.mp4", store, log=lambda text: log.debug(text))
        files = outputs(folder / "video.mp4")
        stored = [("render", files["video"]), ("render", files["poster"]), ("report", files["path"]),
                  ("report", files["summary"])] + ([("render", files["depth"])] if cfg.depth_video else [])
        phase, step = RENDER_PHASE, summary["frames"]
    else:
        store.phase_started(EXPORT_PHASE)
        export(trained, cfg, folder, store)
        target = folder / FILES[cfg.what]
        stored = [("pointcloud" if target.suffix == ".ply" else "report", target), ("report", folder / TRANSFORM),
                  ("report", folder / "export.json")]
        phase, step = EXPORT_PHASE, job.total_steps
    for kind, path in stored:
        store.artifact(kind, path, name=path.name, phase=phase, step=step)


def execute_work(settings: Settings, job: Job, attempt: int, scene_path: str | None) -> str:
    """One claimed attempt of a render or export job; the state it left the job in, or 'lost'."""
    from service.execute import finish, job_cancelled

    url = settings.db_url
    store = DatabaseRunStore(url, str(settings.artifacts), job.id, attempt, settings.retry_s)
    try:
        if scene_path is None:
            raise FileNotFoundError(f"scene {job.scene_id} of job {job.id} no longer exists")
        run(settings, job, attempt, scene_path, store)
    except StopRequested as stopped:
        if job_cancelled(settings, job.id):
            return "cancelled" if finish(settings, job.id, attempt, "cancelled", None) else "lost"
        log.info("job %s attempt %s stopped: %s", job.id, attempt, stopped)
        return "lost"
    except (StaleAttempt, DatabaseUnavailable) as error:
        log.warning("job %s attempt %s gave the job up: %s", job.id, attempt, error)
        reason = f"attempt {attempt} gave up: {error}"
        try:
            retrying(f"handing job {job.id} back to the queue", lambda: queue.release(url, job.id, attempt, reason),
                     settings.retry_s)
        except DatabaseUnavailable:
            pass
        return "lost"
    except Exception as error:
        log.exception("job %s attempt %s failed", job.id, attempt)
        try:
            return "failed" if finish(settings, job.id, attempt, "failed", f"{type(error).__name__}: {error}") \
                else "lost"
        except DatabaseUnavailable:
            return "lost"
    try:
        return "succeeded" if finish(settings, job.id, attempt, "succeeded", None) else "lost"
    except DatabaseUnavailable:
        return "lost"

"""Runs one claimed attempt of a job to its end: train (or resume from the last checkpoint), store the
final artifacts, and move the job to its terminal state. The embedded dispatcher calls `execute` in its own
process; on a cluster the Ray Jobs API runs `python -m service.execute --job-id N --attempt A` on the head
node. Either way the training code is workers.run.run_training, reporting through DatabaseRunStore."""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
from pathlib import Path

from sqlalchemy import select

from service import queue
from service.db import DatabaseUnavailable, reading, retrying
from service.queue import StaleAttempt
from service.runstore import DatabaseRunStore
from service.settings import Settings
from service.store import ArtifactStore, describe
from service.tables import Artifact, Job, Metric, Scene
from workers.config import TrainConfig
from workers.run import SUMMARY, RunError, RunGaveUp, RunInterrupted, run_training

log = logging.getLogger("leco.execute")

FINAL_FILES = (  # (kind, path in the run directory)
    ("checkpoint", "final/models.pt"), ("occupancy_model", "final/occupancy.pt"), ("pointcloud", "occupancy.ply"),
    ("report", "summary.json"), ("report", "eval.json"), ("report", "metrics.jsonl"),
)


def job_dir_for(settings: Settings, job_id: int) -> Path:
    return settings.runs_dir / f"job-{job_id}"


def run_dir_for(settings: Settings, job_id: int, attempt: int) -> Path:
    """Each attempt trains in a folder of its own: an attempt that lost its lease but still runs
    cannot write into the folder its successor resumes in."""
    return job_dir_for(settings, job_id) / f"attempt-{attempt}"


def finish(settings: Settings, job_id: int, attempt: int, state: str, error: str | None) -> bool:
    # A job's end must not be lost to a database restart: wait for it (the lease covers the wait).
    return retrying(f"recording job {job_id} as {state}",
                    lambda: queue.finish(settings.db_url, job_id, attempt, state, error), settings.retry_s)


def execute(settings: Settings, job_id: int, attempt: int) -> str:
    """Returns the state it left the job in, or 'lost' when this attempt no longer holds it."""
    url = settings.db_url
    with reading(url) as session:
        job = session.get(Job, job_id)
        scene_path = session.scalar(select(Scene.path).where(Scene.id == job.scene_id)) if job else None
    if job is None or job.state != "running" or job.attempts != attempt:
        return "lost"
    if job.kind != "train":  # a render or export of a finished training job
        from service.derived import execute_work

        return execute_work(settings, job, attempt, scene_path)
    cfg = TrainConfig.model_validate(job.config)
    if attempt == 1:  # a new job never inherits a folder (a reset database)
        shutil.rmtree(job_dir_for(settings, job_id), ignore_errors=True)
    store = DatabaseRunStore(url, str(settings.artifacts), job_id, attempt, settings.retry_s, settings.keep_checkpoints)
    try:
        run_dir = trained_earlier(settings, job_id, attempt)  # an attempt that trained to the end, died storing
        if run_dir is None:
            run_dir = run_dir_for(settings, job_id, attempt)
            seed = seed_from_store(settings, job_id, run_dir)
            if scene_path is None:  # the scenes foreign key forbids it; should it happen, the job fails saying so
                raise RunError(f"scene {job.scene_id} of job {job_id} no longer exists")
            run_training(cfg, scene_path, run_dir, backend=settings.backend, store=store, resume_from=seed)
        if store.stop_reason() is not None and not job_cancelled(settings, job_id):
            return "lost"
        store_final_artifacts(store, run_dir, cfg)
    except RunInterrupted as stopped:
        if job_cancelled(settings, job_id):
            return "cancelled" if finish(settings, job_id, attempt, "cancelled", None) else "lost"
        log.info("job %s attempt %s stopped: %s", job_id, attempt, stopped)
        return "lost"
    except (RunGaveUp, StaleAttempt, DatabaseUnavailable) as error:
        # Not the job's failure: another attempt holds it, or the database stayed away. Hand the job back to
        # the queue (it resumes from its last stored checkpoint); if the database is still away, the lease
        # lapses and the reaper does the same.
        log.warning("job %s attempt %s gave the job up: %s", job_id, attempt, error)
        try:
            reason = f"attempt {attempt} gave up: {error}"
            retrying(f"handing job {job_id} back to the queue", lambda: queue.release(url, job_id, attempt, reason),
                     settings.retry_s)
        except DatabaseUnavailable:
            pass
        return "lost"
    except Exception as error:  # the job fails with the reason; the service goes on
        log.exception("job %s attempt %s failed", job_id, attempt)
        reason = str(error) if isinstance(error, RunError) else f"{type(error).__name__}: {error}"
        try:
            return "failed" if finish(settings, job_id, attempt, "failed", reason) else "lost"
        except DatabaseUnavailable:
            return "lost"
    try:
        return "succeeded" if finish(settings, job_id, attempt, "succeeded", None) else "lost"
    except DatabaseUnavailable:  # the lease lapses; the next attempt finds the trained folder and stores it
        return "lost"


def trained_earlier(settings: Settings, job_id: int, attempt: int) -> Path | None:
    """The folder of an earlier attempt that finished training (summary.json) but not storing its results."""
    for earlier in range(attempt - 1, 0, -1):
        folder = run_dir_for(settings, job_id, earlier)
        if (folder / SUMMARY).exists():
            return folder
    return None


def seed_from_store(settings: Settings, job_id: int, run_dir: Path) -> Path | None:
    """A later attempt resumes from the job's newest stored checkpoint (written through the fence, so by an
    attempt that held the job) and the metrics stored up to its step; None when there is none yet."""
    def newest() -> dict | None:
        with reading(settings.db_url) as session:
            row = session.scalars(select(Artifact).where(Artifact.job_id == job_id, Artifact.kind == "checkpoint")
                                  .order_by(Artifact.step.desc(), Artifact.id.desc()).limit(1)).first()
            return describe(row) if row else None

    meta = retrying(f"finding job {job_id}'s last checkpoint", newest, settings.retry_s)
    if meta is None:
        return None
    seed = run_dir / "resume-from"
    shutil.rmtree(seed, ignore_errors=True)
    seed.mkdir(parents=True)
    shutil.copyfile(ArtifactStore(settings.db_url, settings.artifacts).verified_path(meta), seed / "state.pt")
    step = int(meta["step"])

    def metrics() -> list[dict]:
        with reading(settings.db_url) as session:
            rows = session.execute(select(Metric.step, Metric.phase, Metric.name, Metric.value, Metric.wall_time_s)
                                   .where(Metric.job_id == job_id, Metric.step <= step).order_by(Metric.step)).all()
        records: dict[int, dict] = {}
        for s, phase, name, value, wall in rows:
            record = records.setdefault(s, {"step": s, "phase": phase})
            record[name] = value
            if wall is not None:
                record["wall_time_s"] = wall
        return list(records.values())

    records = retrying(f"reading job {job_id}'s metrics", metrics, settings.retry_s)
    (run_dir / "metrics.jsonl").write_text("".join(json.dumps(r, sort_keys=True) + "\n" for r in records))
    return seed


def job_cancelled(settings: Settings, job_id: int) -> bool:
    def read() -> bool:
        with reading(settings.db_url) as session:
            return bool(session.scalar(select(Job.cancel_requested).where(Job.id == job_id)))

    return retrying(f"reading job {job_id}", read, settings.retry_s)


def store_final_artifacts(store: DatabaseRunStore, run_dir: Path, cfg: TrainConfig) -> None:
    summary = json.loads((run_dir / SUMMARY).read_text())
    step = summary["steps"]["total"]
    for kind, name in FINAL_FILES:
        if (run_dir / name).is_file():
            store.artifact(kind, run_dir / name, name=name, phase=cfg.phases[-1], step=step)
    for render in sorted((run_dir / "renders").glob("final_*.png")):
        store.artifact("render", render, name=f"renders/{render.name}", phase=cfg.phases[-1], step=step)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="run one claimed attempt of a LeCO service job")
    parser.add_argument("--job-id", type=int, required=True)
    parser.add_argument("--attempt", type=int, required=True)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    state = execute(Settings.from_env(), args.job_id, args.attempt)
    print(f"job {args.job_id} attempt {args.attempt}: {state}")
    return 0 if state in ("succeeded", "cancelled", "lost") else 1


if __name__ == "__main__":
    sys.exit(main())

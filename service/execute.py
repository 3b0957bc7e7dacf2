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
from service.db import reading, retrying
from service.runstore import DatabaseRunStore
from service.settings import Settings
from service.tables import Job, Scene
from workers.config import TrainConfig
from workers.run import SUMMARY, RunError, RunInterrupted, run_training

log = logging.getLogger("leco.execute")

FINAL_FILES = (  # (kind, path in the run directory)
    ("checkpoint", "final/models.pt"), ("occupancy_model", "final/occupancy.pt"), ("pointcloud", "occupancy.ply"),
    ("report", "summary.json"), ("report", "eval.json"), ("report", "metrics.jsonl"),
)


def run_dir_for(settings: Settings, job_id: int) -> Path:
    return settings.runs_dir / f"job-{job_id}"


def finish(url: str, job_id: int, attempt: int, state: str, error: str | None) -> bool:
    # A job's end must not be lost to a database restart: wait for it (the lease covers the wait).
    return retrying(f"recording job {job_id} as {state}", lambda: queue.finish(url, job_id, attempt, state, error))


def execute(settings: Settings, job_id: int, attempt: int) -> str:
    """Returns the state it left the job in, or 'lost' when this attempt no longer holds it."""
    url = settings.db_url
    with reading(url) as session:
        job = session.get(Job, job_id)
        scene_path = session.scalar(select(Scene.path).where(Scene.id == job.scene_id)) if job else None
    if job is None or job.state != "running" or job.attempts != attempt:
        return "lost"
    cfg = TrainConfig.model_validate(job.config)
    run_dir = run_dir_for(settings, job_id)
    if attempt == 1:
        shutil.rmtree(run_dir, ignore_errors=True)  # a new job never inherits a folder (a reset database)
    store = DatabaseRunStore(url, str(settings.artifacts), job_id, attempt, settings.keep_checkpoints)
    try:
        if not (run_dir / SUMMARY).exists():  # else an earlier attempt trained to the end and died before storing
            run_training(cfg, scene_path, run_dir, backend=settings.backend, store=store)
        if store.stop_reason() is not None and not job_cancelled(url, job_id):
            return "lost"
        store_final_artifacts(store, run_dir, cfg)
    except RunInterrupted as stopped:
        if job_cancelled(url, job_id):
            return "cancelled" if finish(url, job_id, attempt, "cancelled", None) else "lost"
        log.info("job %s attempt %s stopped: %s", job_id, attempt, stopped)
        return "lost"
    except Exception as error:  # the job fails with the reason; the service goes on
        log.exception("job %s attempt %s failed", job_id, attempt)
        reason = str(error) if isinstance(error, RunError) else f"{type(error).__name__}: {error}"
        return "failed" if finish(url, job_id, attempt, "failed", reason) else "lost"
    return "succeeded" if finish(url, job_id, attempt, "succeeded", None) else "lost"


def job_cancelled(url: str, job_id: int) -> bool:
    def read() -> bool:
        with reading(url) as session:
            return bool(session.scalar(select(Job.cancel_requested).where(Job.id == job_id)))

    return retrying(f"reading job {job_id}", read)


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

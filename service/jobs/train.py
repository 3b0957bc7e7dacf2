"""A training job's work: train (or resume from the job's last stored checkpoint) with
workers.train.run, then store the final artifacts. The attempt runner (attempt.py) turns how it ends
into the job's state."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from sqlalchemy import select

from service.db import reading, retrying
from service.jobs.context import Attempt
from service.jobs.paths import job_dir_for, run_dir_for
from service.runstore import DatabaseRunStore
from service.settings import Settings
from service.store import ArtifactStore, describe
from service.tables import Artifact, Metric
from workers.config import TrainConfig
from workers.train.run import SUMMARY, RunInterrupted, run_training

FINAL_FILES = (  # (kind, path in the run directory)
    ("checkpoint", "final/models.pt"),
    ("occupancy_model", "final/occupancy.pt"),
    ("pointcloud", "occupancy.ply"),
    ("report", "summary.json"),
    ("report", "eval.json"),
    ("report", "metrics.jsonl"),
)


def train(attempt: Attempt) -> None:
    settings, job_id, number = attempt.settings, attempt.job.id, attempt.number
    cfg = TrainConfig.model_validate(attempt.job.config)
    if number == 1:  # a new job never inherits a folder (a reset database)
        shutil.rmtree(job_dir_for(settings, job_id), ignore_errors=True)
    # an attempt that trained to the end, died storing
    run_dir = trained_earlier(settings, job_id, number)
    if run_dir is None:
        run_dir = run_dir_for(settings, job_id, number)
        seed = seed_from_store(settings, job_id, run_dir)
        run_training(
            cfg,
            attempt.scene_path,
            run_dir,
            backend=settings.backend,
            store=attempt.store,
            resume_from=seed,
        )
    reason = attempt.store.stop_reason()
    if reason is not None and not attempt.cancelled():
        raise RunInterrupted(reason)
    store_final_artifacts(attempt.store, run_dir, cfg)


def trained_earlier(settings: Settings, job_id: int, attempt: int) -> Path | None:
    """The folder of an earlier attempt that finished training (summary.json) but not storing its
    results."""
    for earlier in range(attempt - 1, 0, -1):
        folder = run_dir_for(settings, job_id, earlier)
        if (folder / SUMMARY).exists():
            return folder
    return None


def seed_from_store(settings: Settings, job_id: int, run_dir: Path) -> Path | None:
    """A later attempt resumes from the job's newest stored checkpoint (written through the fence,
    so by an attempt that held the job) and the metrics stored up to its step; None when there is
    none yet."""

    def newest() -> dict | None:
        with reading(settings.db_url) as session:
            row = session.scalars(
                select(Artifact)
                .where(Artifact.job_id == job_id, Artifact.kind == "checkpoint")
                .order_by(Artifact.step.desc(), Artifact.id.desc())
                .limit(1)
            ).first()
            return describe(row) if row else None

    meta = retrying(f"finding job {job_id}'s last checkpoint", newest, settings.retry_s)
    if meta is None:
        return None
    seed = run_dir / "resume-from"
    shutil.rmtree(seed, ignore_errors=True)
    seed.mkdir(parents=True)
    shutil.copyfile(
        ArtifactStore(settings.db_url, settings.artifacts).verified_path(meta), seed / "state.pt"
    )
    step = int(meta["step"])

    def metrics() -> list[dict]:
        with reading(settings.db_url) as session:
            rows = session.execute(
                select(Metric.step, Metric.phase, Metric.name, Metric.value, Metric.wall_time_s)
                .where(Metric.job_id == job_id, Metric.step <= step)
                .order_by(Metric.step)
            ).all()
        records: dict[int, dict] = {}
        for s, phase, name, value, wall in rows:
            record = records.setdefault(s, {"step": s, "phase": phase})
            record[name] = value
            if wall is not None:
                record["wall_time_s"] = wall
        return list(records.values())

    records = retrying(f"reading job {job_id}'s metrics", metrics, settings.retry_s)
    (run_dir / "metrics.jsonl").write_text(
        "".join(json.dumps(r, sort_keys=True) + "\n" for r in records)
    )
    return seed


def store_final_artifacts(store: DatabaseRunStore, run_dir: Path, cfg: TrainConfig) -> None:
    summary = json.loads((run_dir / SUMMARY).read_text())
    step = summary["steps"]["total"]
    for kind, name in FINAL_FILES:
        if (run_dir / name).is_file():
            store.artifact(kind, run_dir / name, name=name, phase=cfg.phases[-1], step=step)
    for render in sorted((run_dir / "renders").glob("final_*.png")):
        store.artifact(
            "render", render, name=f"renders/{render.name}", phase=cfg.phases[-1], step=step
        )

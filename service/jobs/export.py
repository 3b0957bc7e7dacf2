"""An export job's work: geometry of its finished training job in the dataset's own frame (workers/export.py),
its files stored by name at the end, so a retried attempt replaces them."""

from __future__ import annotations

import shutil

from service.jobs.attempt import Attempt
from service.jobs.parent import load_parent
from service.jobs.paths import run_dir_for
from workers.export import FILES, TRANSFORM
from workers.export import export as export_geometry
from workers.render_config import EXPORT_PHASE, ExportConfig


def export(attempt: Attempt) -> None:
    job, store = attempt.job, attempt.store
    folder = run_dir_for(attempt.settings, job.id, attempt.number)
    shutil.rmtree(folder, ignore_errors=True)
    assert job.parent_id is not None
    trained = load_parent(attempt.settings, job.parent_id, attempt.scene_path, folder)
    cfg = ExportConfig.model_validate(job.config)
    store.phase_started(EXPORT_PHASE)
    export_geometry(trained, cfg, folder, store)
    target = folder / FILES[cfg.what]
    stored = [("pointcloud" if target.suffix == ".ply" else "report", target), ("report", folder / TRANSFORM),
              ("report", folder / "export.json")]
    for kind, path in stored:
        store.artifact(kind, path, name=path.name, phase=EXPORT_PHASE, step=job.total_steps)

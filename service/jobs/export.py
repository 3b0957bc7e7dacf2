"""An export job's work: geometry of its finished training job in the dataset's own frame
(workers/render/export.py), its files stored by name at the end, so a retried attempt replaces
them."""

from __future__ import annotations

from service.jobs.context import Attempt
from service.jobs.parent import parent_of
from workers.render.export import FILES, TRANSFORM
from workers.render.export import export as export_geometry
from workers.render.schemas import EXPORT_PHASE, ExportConfig


def export(attempt: Attempt) -> None:
    job, store = attempt.job, attempt.store
    folder, trained = parent_of(attempt)
    cfg = ExportConfig.model_validate(job.config)
    store.phase_started(EXPORT_PHASE)
    export_geometry(trained, cfg, folder, store)
    target = folder / FILES[cfg.what]
    stored = [
        ("pointcloud" if target.suffix == ".ply" else "report", target),
        ("report", folder / TRANSFORM),
        ("report", folder / "export.json"),
    ]
    for kind, path in stored:
        store.artifact(kind, path, name=path.name, phase=EXPORT_PHASE, step=job.total_steps)

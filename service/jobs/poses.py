"""A poses job's work: pycolmap on a scene's uploaded photos (workers/poses) in a process of
its own, each stage a phase counted in percent. The posed folder appears as the scene's folder
and the scene becomes ready; what the photos got wrong fails the job and the scene with the
reason. A later attempt (after a restart or a lost lease) goes on from the last finished stage."""

from __future__ import annotations

import json
import logging
import shutil

from model.errors import Failed, InvalidInput
from service.db import transaction
from service.jobs.context import Attempt, job_cancelled
from service.scenes import describe_folder, layout_path, photos_path, write_layout
from service.tables import Scene
from workers.poses.pipeline import REPORT
from workers.poses.process import PosesCancelled, run_poses
from workers.poses.settings import STAGE_STEPS, STAGES, PosesConfig
from workers.store import RunError, RunGaveUp, StopRequested, StoreWriteError

log = logging.getLogger("leco.poses")


class StageProgress:
    """Pipeline events -> the job's phases: a stage's percent is its phase's step, and the job's
    step is the stages before it (100 each) plus that percent."""

    def __init__(self, attempt: Attempt):
        self.store = attempt.store
        self.stage = STAGES[0]
        self.written = -1

    def __call__(self, event: dict) -> None:
        kind = event["event"]
        if kind == "stage":
            self.stage = event["stage"]
            self.store.phase_started(self.stage)
            self._write(0)
        elif kind == "progress":
            self._write(int(STAGE_STEPS * event["done"] / max(event["total"], 1)))
        else:
            log.info("poses: %s%s", "warning: " if kind == "warning" else "", event["message"])

    def _write(self, percent: int) -> None:
        step = STAGES.index(self.stage) * STAGE_STEPS + percent
        if step == self.written:
            return
        self.written = step
        self.store.write(step, {"phase": self.stage, "phase_step": percent, "percent": percent})


def _scene_ends(attempt: Attempt, state: str, **fields: object) -> None:
    with transaction(attempt.settings.db_url) as session:
        row = session.get(Scene, attempt.job.scene_id)
        if row is not None:
            row.state = state
            for name, value in fields.items():
                setattr(row, name, value)


def poses(attempt: Attempt) -> None:
    settings, store = attempt.settings, attempt.store
    config = PosesConfig.model_validate(attempt.job.config)
    scene_id = attempt.job.scene_id
    photos, out = photos_path(settings, scene_id), settings.scenes_dir / f"scene-{scene_id}"
    try:
        if (out / REPORT).is_file():  # an attempt that exported and then died before the row
            summary = json.loads((out / REPORT).read_text())
        else:
            summary = run_poses(
                photos, out, config, StageProgress(attempt), lambda: store.stop_reason() is not None
            )
    except (RunGaveUp, StoreWriteError):  # the store's, not the photos': the queue decides
        raise
    except PosesCancelled:
        if job_cancelled(settings, attempt.job.id):
            _scene_ends(attempt, "failed", error="posing was cancelled")
        raise StopRequested(store.stop_reason() or "stopped") from None
    except (InvalidInput, Failed) as error:
        reason = str(error).replace(f"{photos}/", "")  # a photo by its name in the archive
        _scene_ends(attempt, "failed", error=f"posing failed: {reason}")
        raise RunError(reason) from None
    info, layout = describe_folder(out, settings.max_scene_pixels)
    write_layout(layout_path(settings, scene_id), layout)
    _scene_ends(attempt, "ready", format=info["format"], info={**info, "poses": summary})
    store.write(len(STAGES) * STAGE_STEPS, {"phase": STAGES[-1], "phase_step": STAGE_STEPS})
    shutil.rmtree(photos, ignore_errors=True)  # the scene's images/ holds the registered ones

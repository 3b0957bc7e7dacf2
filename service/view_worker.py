"""The process side of `POST /v1/jobs/{id}/view`: one camera of a finished training job rendered
to PNG in a process of the view pool, never in the API process. Each process keeps the networks of the last
few jobs it rendered loaded, so the viewer's next frame costs a render, not a load."""

from __future__ import annotations

import io
import time
from collections import OrderedDict
from pathlib import Path

from PIL import Image
from sqlalchemy import select

from service.db import reading
from service.settings import Settings
from service.tables import Job, Scene
from workers.trained import Trained

LOADED_JOBS = 2
_loaded: OrderedDict[int, Trained] = OrderedDict()


def trained_job(settings: Settings, job_id: int) -> Trained:
    from service.derived import load_parent

    if job_id in _loaded:
        _loaded.move_to_end(job_id)
        return _loaded[job_id]
    with reading(settings.db_url) as session:
        job = session.get(Job, job_id)
        scene_path = session.scalar(select(Scene.path).where(Scene.id == job.scene_id)) if job else None
    if job is None or scene_path is None:
        raise FileNotFoundError(f"job {job_id} or its scene no longer exists")
    trained = load_parent(settings, job_id, scene_path, Path(settings.data_dir) / "views" / f"job-{job_id}")
    _loaded[job_id] = trained
    while len(_loaded) > LOADED_JOBS:
        _loaded.popitem(last=False)
    return trained


def render_view(settings: Settings, job_id: int, body: dict) -> tuple[bytes, float]:
    """(PNG bytes, seconds the render took) of the camera in `body` (a workers.render_config.ViewRequest)."""
    from model.camera_paths import intrinsics_for_fov, user_path
    from workers.frames import appearance_row, depth_uint8, render_frame, to_uint8
    from workers.render_config import ViewRequest

    request = ViewRequest.model_validate(body)
    trained = trained_job(settings, job_id)
    camera, w, h = request.camera, request.width, request.height
    intrinsics = camera.intrinsics or intrinsics_for_fov(camera.fov_deg, w, h).tolist()
    path = user_path([camera.c2w], [intrinsics], w, h,
                     trained.scene.normalization if request.frame == "source" else None, field="camera")
    started = time.perf_counter()
    frame = render_frame(trained, path.cameras(), 0, appearance_row(trained, request.appearance))
    seconds = time.perf_counter() - started
    if request.depth:
        seen = frame.depth[frame.opacity > 0.5] / frame.opacity[frame.opacity > 0.5]
        near, far = (float(seen.min()), float(seen.max())) if len(seen) else (0.0, 1.0)
        pixels = depth_uint8(frame, near, far)
    else:
        pixels = to_uint8(frame.rgb)
    out = io.BytesIO()
    Image.fromarray(pixels.numpy()).save(out, format="PNG")
    return out.getvalue(), seconds

"""One camera of a trained run rendered to a PNG preview (the dashboard's viewer, POST
/v1/jobs/{id}/view)."""

from __future__ import annotations

import io
import time

from PIL import Image

from model.scenes.camera_paths import intrinsics_for_fov, user_path
from workers.render.frames import appearance_row, render_frame
from workers.render.schemas import ViewRequest
from workers.renderer import depth_grey, depth_range, to_uint8
from workers.trained import Trained


def render_view_png(trained: Trained, request: ViewRequest) -> tuple[bytes, float]:
    """(PNG bytes, seconds the render took). A depth view spans the depths it sees
    (workers/renderer.py)."""
    camera, w, h = request.camera, request.width, request.height
    intrinsics = camera.intrinsics or intrinsics_for_fov(camera.fov_deg, w, h).tolist()
    path = user_path(
        [camera.c2w],
        [intrinsics],
        w,
        h,
        trained.scene.normalization if request.frame == "source" else None,
        field="camera",
    )
    started = time.perf_counter()
    frame = render_frame(trained, path.cameras(), 0, appearance_row(trained, request.appearance))
    seconds = time.perf_counter() - started
    pixels = depth_grey(frame, *depth_range(frame)) if request.depth else to_uint8(frame.rgb)
    out = io.BytesIO()
    Image.fromarray(pixels.numpy()).save(out, format="PNG")
    return out.getvalue(), seconds

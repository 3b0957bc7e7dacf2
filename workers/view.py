"""One camera of a trained run rendered to a PNG preview (the dashboard's viewer, POST /v1/jobs/{id}/view)."""

from __future__ import annotations

import io
import time

from PIL import Image

from model.camera_paths import intrinsics_for_fov, user_path
from workers.frames import appearance_row, depth_uint8, render_frame, to_uint8
from workers.render_config import ViewRequest
from workers.trained import Trained


def render_view_png(trained: Trained, request: ViewRequest) -> tuple[bytes, float]:
    """(PNG bytes, seconds the render took). A depth view spans the depths it sees."""
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

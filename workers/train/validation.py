"""Whole validation images rendered with a run's current networks (workers/renderer.py: no gradient,
no jitter), and the PNGs a person looks at: prediction, ground truth and depth side by side."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image

from model.methods import Method
from model.methods.base import Networks
from model.scenes.rays import PixelTable
from model.scenes.scene import Views
from workers.models import LiveNetworks
from workers.renderer import Rendering, depth_grey, depth_range, render_rays, to_uint8


def render_image(
    method: Method,
    models: Networks,
    phase: str,
    table: PixelTable,
    image: int,
    aabb: torch.Tensor,
    device: torch.device,
    columns: tuple[int, int] | None = None,
) -> Rendering:
    """A whole validation image, or its columns u0 <= u < u1, shaped (H, W')."""
    rendered = render_rays(method, models, phase, table.image_rays(image, aabb, columns), device)
    h = int(table.views.cameras.height[image])
    return rendered.reshape(h, len(rendered.depth) // h)


def save_triptych(path: Path, prediction: Rendering, truth: torch.Tensor) -> None:
    panels = [to_uint8(prediction.rgb), truth, depth_grey(prediction, *depth_range(prediction))]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.png")
    Image.fromarray(np.concatenate([p.numpy() for p in panels], axis=1)).save(tmp)
    tmp.replace(path)


def write_validation_renders(
    live: LiveNetworks, phase: str, views: Views, run_dir: Path, step: int
) -> Path:
    """During training: the first of `views` (the validation views, or the training views when the
    scene has no val split) as RUN_DIR/renders/step<step>_<name>.png."""
    rendered = render_image(
        live.method, live.models, phase, PixelTable(views), 0, live.aabb, live.device
    )
    path = run_dir / "renders" / f"step{step:07d}_{views.names[0]}.png"
    save_triptych(path, rendered, views.image(0))
    return path

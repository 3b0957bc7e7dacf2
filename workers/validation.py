"""Rendering whole validation images with a run's current networks (no gradient, no jitter), and the PNGs
a person looks at: prediction, ground truth and depth side by side."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image

from model.methods import Method
from model.scenes.rays import PixelTable, RayBatch

CHUNK = 4096  # rays per forward pass while rendering an image


@torch.no_grad()
def render_rays(method: Method, models, phase: str, rays: RayBatch) -> tuple[torch.Tensor, torch.Tensor]:
    """(rgb (R, 3), depth (R,)) with the networks of `phase` in eval mode."""
    was = models.training
    models.eval()
    try:
        rendered = method.render(models, phase, rays)
    finally:
        models.train(was)
    return rendered.rgb.float().clamp(0, 1), rendered.depth.float()


def render_image(method: Method, models, phase: str, table: PixelTable, image: int, aabb,
                 device, columns: tuple[int, int] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """A whole validation image, or its columns u0 <= u < u1: (rgb (H, W', 3), depth (H, W'))."""
    rays = table.image_rays(image, aabb, columns)
    rgb, depth = [], []
    for s in range(0, len(rays), CHUNK):
        chunk = RayBatch(*(getattr(rays, f)[s : s + CHUNK] for f in RayBatch.__dataclass_fields__)).to(device)
        c, d = render_rays(method, models, phase, chunk)
        rgb.append(c.cpu())
        depth.append(d.cpu())
    h = int(table.views.cameras.height[image])
    return torch.cat(rgb).reshape(h, -1, 3), torch.cat(depth).reshape(h, -1)


def depth_to_image(depth: torch.Tensor) -> np.ndarray:
    """Depth as an 8-bit grey image: near is bright, normalised by the 1st-99th percentile."""
    d = depth.float()
    lo, hi = torch.quantile(d.reshape(-1), 0.01), torch.quantile(d.reshape(-1), 0.99)
    scaled = 1.0 - ((d - lo) / (hi - lo).clamp(min=1e-8)).clamp(0, 1)
    return (scaled * 255).round().byte().numpy()


def save_triptych(path: Path, prediction: torch.Tensor, truth: torch.Tensor, depth: torch.Tensor) -> None:
    grey = depth_to_image(depth)
    panels = [(prediction * 255).round().byte().numpy(), truth.numpy(), np.repeat(grey[..., None], 3, -1)]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.png")
    Image.fromarray(np.concatenate(panels, axis=1)).save(tmp)
    tmp.replace(path)


def write_validation_renders(run, step: int) -> Path:
    """During training: the first validation view (or training view when the scene has no val split)."""
    views = run.scene.splits.get("val", run.scene.train)
    table = PixelTable(views)
    rgb, depth = render_image(run.method, run.models, run.progress["phase"], table, 0, run.aabb, run.device)
    path = run.run_dir / "renders" / f"step{step:07d}_{views.names[0]}.png"
    save_triptych(path, rgb, views.image(0), depth)
    return path

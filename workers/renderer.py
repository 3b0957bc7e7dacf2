"""The one renderer: rays, or every pixel of a camera, in; colour, depth and opacity out. It renders
in chunks of rays without gradient, by the method's own sampler (`Method.render`), with the phase's
networks in eval mode. Validation images, video frames, the viewer's previews, exported point clouds
and the benchmark's reference depth maps all go through it, and depth becomes a picture by one rule
(`depth_range`, `depth_grey`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import torch
from torch import Tensor, nn

from model.methods import Method
from model.scenes.bounds import ray_aabb
from model.scenes.cameras import Cameras, pixel_rays
from model.scenes.rays import RayBatch

CHUNK = 4096  # rays per forward pass (no gradient: the memory is one chunk's activations)
SURFACE_OPACITY = 0.5  # a ray less opaque than this saw no surface (the background shows there)


@dataclass
class Rendering:
    rgb: Tensor  # (..., 3) in [0, 1]
    depth: Tensor  # (...,) sum of w t: the distance along the unit ray, weighted by the opacity
    opacity: Tensor  # (...,) the foreground's accumulated opacity
    samples_per_ray: float  # main-network samples the method spent per ray

    def reshape(self, height: int, width: int) -> Rendering:
        return Rendering(
            self.rgb.reshape(height, width, 3),
            self.depth.reshape(height, width),
            self.opacity.reshape(height, width),
            self.samples_per_ray,
        )

    def surface_distance(self, min_opacity: float = SURFACE_OPACITY) -> Tensor:
        """The expected distance of the surface a ray hits (depth over opacity, in float64), inf on
        rays less opaque than `min_opacity`."""
        distance = self.depth.double() / self.opacity.double().clamp(min=1e-6)
        return torch.where(self.opacity >= min_opacity, distance, torch.inf)


def chunks(rays: RayBatch, size: int) -> Iterator[RayBatch]:
    for start in range(0, len(rays), size):
        yield RayBatch(
            *(getattr(rays, f)[start : start + size] for f in RayBatch.__dataclass_fields__)
        )


@torch.no_grad()
def render_rays(
    method: Method,
    models: nn.Module,
    phase: str,
    rays: RayBatch,
    device: torch.device | str = "cpu",
    chunk: int = CHUNK,
) -> Rendering:
    """`rays` rendered with the networks of `phase`, on the CPU."""
    was = models.training
    models.eval()
    # the outputs are allocated once, before the chunks: a frame holds its pixels once (no
    # concatenation's second copy), and no chunk's output lands between two chunks' activations,
    # so the heap those activations freed is reused as it is (the peak is one chunk over the pixels)
    n = len(rays)
    rgb, depth, opacity = torch.empty(n, 3), torch.empty(n), torch.empty(n)
    samples = 0
    try:
        for start, part in zip(range(0, n, chunk), chunks(rays, chunk)):
            out = method.render(models, phase, part.to(device))
            end = start + len(part)
            rgb[start:end] = out.rgb.float().clamp(0, 1).cpu()
            depth[start:end] = out.depth.float().cpu()
            opacity[start:end] = out.opacity.float().cpu()
            samples += out.weights.numel()
    finally:
        models.train(was)
    return Rendering(rgb, depth, opacity, samples / n if n else 0.0)


def camera_rays(cameras: Cameras, index: int, aabb: Tensor, appearance: int) -> RayBatch:
    """Every pixel of camera `index`, row by row, with appearance-embedding row `appearance`."""
    width, height = int(cameras.width[index]), int(cameras.height[index])
    v, u = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    cam = torch.full((width * height,), index, dtype=torch.long)
    origins, directions = pixel_rays(cameras, cam, u.reshape(-1), v.reshape(-1))
    origins, directions = origins.float(), directions.float()
    near, far = ray_aabb(origins, directions, aabb)
    n = width * height
    return RayBatch(
        origins,
        directions,
        near,
        far,
        torch.full((n,), appearance, dtype=torch.long),
        torch.zeros(n, 3),
        torch.arange(n),
    )


def depth_range(rendering: Rendering) -> tuple[float, float]:
    """The 1st and 99th percentiles of the surface distances a rendering sees; (0, 1) when it sees
    none."""
    seen = rendering.surface_distance()
    seen = seen[torch.isfinite(seen)].float()
    if len(seen) == 0:
        return 0.0, 1.0
    return float(torch.quantile(seen, 0.01)), float(torch.quantile(seen, 0.99))


def depth_grey(rendering: Rendering, near: float, far: float) -> Tensor:
    """Depth as grey (H, W, 3) uint8 on the range [near, far], near bright, faded to black as the
    foreground turns transparent. A video passes one range for all its frames, so their brightness
    does not flicker."""
    distance = (rendering.depth / rendering.opacity.clamp(min=1e-6)).float()
    scaled = 1.0 - ((distance - near) / max(far - near, 1e-8)).clamp(0, 1)
    grey = (scaled * rendering.opacity.clamp(0, 1) * 255).round().byte()
    return grey[..., None].expand(*grey.shape, 3).contiguous()


def to_uint8(rgb: Tensor) -> Tensor:
    return (rgb * 255).round().clamp(0, 255).byte()

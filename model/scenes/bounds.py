"""Automatic foreground bounds: from the cameras and whatever geometry the dataset carries, never
from a hand-set box or altitude range. The rule (docs/SCENES.md):

1. Evidence points, from the best source present: ground-truth depth maps (back-projected train
   pixels), else sparse SfM points, else LLFF per-image depth bounds, else the convergence of the
   cameras' optical axes (each crossing point grown by the image footprint at its distance).
2. Keep points within FAR_FACTOR x the median distance to their nearest camera: surfaces seen much
   farther away than typical (the ground out to the horizon) are coarsely resolved anyway and belong
   to the background model, which covers everything outside the box. Surface evidence (depth maps,
   SfM points) must also be in view of at least COVERAGE_RATIO x the median point's share of the
   cameras: what few views cover is poorly constrained and goes to the background too.
3. Box = min/max of exact evidence (depth maps), or 0.5/99.5 percentiles per axis of estimated
   evidence (SfM outliers), padded by MARGIN of its extent on every side, no side thinner than
   MIN_SIDE of the longest.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from model.scenes.cameras import Cameras, pixel_rays
from model.scenes.errors import SceneError
from model.scenes.source import SourceScene

FAR_FACTOR = 2.5
COVERAGE_RATIO = 0.5
MAX_COVERAGE_CAMERAS = 256
MARGIN = 0.05
MIN_SIDE = 0.05
MAX_DEPTH_POINTS = 200_000
MIN_AXIS_ANGLE_DEG = 10.0
AXIS_MISS_RATIO = 0.25
MAX_AXIS_CAMERAS = 64


def depth_points(
    cameras: Cameras, depth: Sequence[Tensor], budget: int = MAX_DEPTH_POINTS
) -> Tensor:
    """Surface points from depth maps, on a regular pixel stride so the total stays within
    budget."""
    total = sum(d.numel() for d in depth)
    stride = max(1, int((total / budget) ** 0.5 + 0.999))
    points = []
    for i, d in enumerate(depth):
        v, u = torch.meshgrid(
            torch.arange(0, d.shape[0], stride), torch.arange(0, d.shape[1], stride), indexing="ij"
        )
        t = d[v, u].reshape(-1)
        keep = torch.isfinite(t) & (t > 0)
        cam = torch.full((int(keep.sum()),), i, dtype=torch.long)
        o, dirs = pixel_rays(cameras, cam, u.reshape(-1)[keep], v.reshape(-1)[keep])
        points.append(o.double() + dirs.double() * t[keep, None].double())
    return torch.cat(points) if points else torch.zeros(0, 3, dtype=torch.float64)


def axis_convergence_points(cameras: Cameras) -> Tensor:
    """Where pairs of optical axes (nearly) cross, each grown by the image half-footprint at that
    range."""
    n = len(cameras)
    pick = torch.linspace(0, n - 1, min(n, MAX_AXIS_CAMERAS)).round().long().unique()
    o = cameras.centers[pick].double()
    f = cameras.forward[pick].double()
    tan_half = torch.tan(cameras.half_fov()[pick].double())
    i, j = torch.triu_indices(len(pick), len(pick), offset=1)
    cos = (f[i] * f[j]).sum(-1)
    w0 = o[i] - o[j]
    b, d, e = cos, (f[i] * w0).sum(-1), (f[j] * w0).sum(-1)
    denom = 1 - b * b
    ok = cos < torch.cos(torch.deg2rad(torch.tensor(MIN_AXIS_ANGLE_DEG, dtype=torch.float64)))
    denom = torch.where(ok, denom, torch.ones_like(denom))
    ti = (b * e - d) / denom  # closest points of two lines, unit directions
    tj = (e - b * d) / denom
    pi, pj = o[i] + ti[:, None] * f[i], o[j] + tj[:, None] * f[j]
    miss = (pi - pj).norm(dim=-1)
    ok &= (ti > 0) & (tj > 0) & (miss <= AXIS_MISS_RATIO * 0.5 * (ti + tj))
    if not bool(ok.any()):
        return torch.zeros(0, 3, dtype=torch.float64)
    mid = 0.5 * (pi + pj)[ok]
    radius = (0.5 * (ti * tan_half[i] + tj * tan_half[j]))[ok]
    offsets = torch.cat([torch.zeros(1, 3), torch.eye(3), -torch.eye(3)]).double()
    return (mid[:, None, :] + radius[:, None, None] * offsets[None]).reshape(-1, 3)


def nearest_camera_distance(points: Tensor, centers: Tensor, chunk: int = 65536) -> Tensor:
    out = [
        torch.cdist(points[s : s + chunk], centers.double()).amin(dim=1)
        for s in range(0, len(points), chunk)
    ]
    return torch.cat(out) if out else torch.zeros(0, dtype=torch.float64)


def coverage(points: Tensor, cameras: Cameras, chunk: int = 4096) -> Tensor:
    """Share of the cameras (at most MAX_COVERAGE_CAMERAS, evenly picked) whose image each point
    falls in."""
    pick = (
        torch.linspace(0, len(cameras) - 1, min(len(cameras), MAX_COVERAGE_CAMERAS))
        .round()
        .long()
        .unique()
    )
    c2w = cameras.c2w[pick].double()
    fx, fy, cx, cy = cameras.intrinsics[pick].double().unbind(-1)
    width, height = cameras.width[pick].double(), cameras.height[pick].double()
    out = []
    for s in range(0, len(points), chunk):
        rel = points[s : s + chunk, None, :] - c2w[None, :, :, 3]
        local = torch.einsum("pci,cij->pcj", rel, c2w[:, :, :3])  # camera frame: right, up, back
        depth = -local[..., 2]
        safe = depth.clamp(min=1e-9)
        u = fx * local[..., 0] / safe + cx
        v = -fy * local[..., 1] / safe + cy
        seen = (depth > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        out.append(seen.double().mean(dim=1))
    return torch.cat(out) if out else torch.zeros(0, dtype=torch.float64)


def evidence(source: SourceScene) -> tuple[Tensor, str, bool]:
    """(points, kind, exact) from the best evidence the dataset carries."""
    train = source.splits["train"]
    if train.depth is not None:
        return depth_points(train.cameras, train.depth), "gt_depth", True
    if source.points is not None and len(source.points) > 0:
        return source.points.double(), source.points_kind or "sparse_points", False
    return axis_convergence_points(train.cameras), "camera_axes", False


def foreground_aabb(source: SourceScene) -> tuple[Tensor, str, int]:
    """The foreground box in the rotated source frame, the evidence kind and how many points set
    it."""
    points, kind, exact = evidence(source)
    if len(points) == 0:
        raise SceneError(
            source.root,
            "cannot find the foreground: the cameras' optical axes never cross and the dataset has "
            "no depth maps or sparse points to bound the scene",
        )
    centers = torch.cat([s.cameras.centers for s in source.splits.values()])
    dist = nearest_camera_distance(points, centers)
    keep = dist <= FAR_FACTOR * dist.median()
    if kind in ("gt_depth", "sparse_points"):
        share = coverage(points, source.splits["train"].cameras)
        keep &= share >= COVERAGE_RATIO * share.median()
    points = points[keep]
    if len(points) == 0:
        raise SceneError(
            source.root, f"cannot find the foreground: no {kind} evidence point is near the cameras"
        )
    if exact:
        lo, hi = points.amin(0), points.amax(0)
    else:
        q = torch.tensor([0.005, 0.995], dtype=torch.float64)
        # torch.quantile has an input-size limit
        sample = points[:: max(1, len(points) // 1_000_000)]
        lo, hi = torch.quantile(sample, q, dim=0)
    extent = hi - lo
    if not bool(torch.isfinite(extent).all()) or float(extent.max()) <= 0:
        raise SceneError(
            source.root,
            f"cannot find the foreground: its {len(points):,} {kind} evidence point(s) span no "
            "volume (a single point, or all in one place)",
        )
    lo, hi = lo - MARGIN * extent, hi + MARGIN * extent
    pad = (MIN_SIDE * (hi - lo).max() - (hi - lo)).clamp(min=0) / 2
    # float64: source coordinates can be large
    return torch.stack([lo - pad, hi + pad]), kind, len(points)


def ray_aabb(origins: Tensor, directions: Tensor, aabb: Tensor) -> tuple[Tensor, Tensor]:
    """Foreground segment [near, far] of each ray (slab test). A ray that misses gets near = far =
    0, an empty foreground segment: all of it lies in the background."""
    safe = torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
    inv = 1.0 / safe
    t0 = (aabb[0] - origins) * inv
    t1 = (aabb[1] - origins) * inv
    near = torch.minimum(t0, t1).amax(dim=-1).clamp(min=0.0)
    far = torch.maximum(t0, t1).amin(dim=-1)
    hit = far > near
    zero = torch.zeros_like(near)
    return torch.where(hit, near, zero), torch.where(hit, far, zero)

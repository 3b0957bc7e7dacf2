"""The paper's occupancy protocol (section 4.1): a reference grid from depth maps, the predictor sampled into
the same grid, then accuracy / precision / recall / F1.

Real scenes have no ground truth, so the reference comes from depth maps (the paper uses a fully trained
vanilla Switch-NeRF's; a synthetic scene ships exact ones). Only the cells the depth maps can speak for are
compared: a cell holding a depth point is occupied, a cell some ray crossed before its depth point is free,
and cells no ray saw (inside buildings, behind walls) are left out, so neither method is judged on them.
"""

from __future__ import annotations

from typing import Callable, Sequence

import torch
from torch import Tensor

from model.metrics import occupancy_metrics
from model.scenes.rays import PixelTable
from model.scenes.scene import OccupancyGrid, Views

CHUNK = 1 << 15  # rays per chunk while marking crossed cells
NUDGE = 0.5  # march steps (a quarter cell) behind the visible surface


def cell_index(points: Tensor, aabb: Tensor, resolution: int) -> tuple[Tensor, Tensor]:
    """Flat cell index of each point in a resolution^3 grid over aabb, and whether the point is inside."""
    u = (points - aabb[0]) / (aabb[1] - aabb[0])
    inside = ((u >= 0) & (u < 1)).all(-1)
    ijk = (u * resolution).long().clamp(0, resolution - 1)
    return (ijk[:, 0] * resolution + ijk[:, 1]) * resolution + ijk[:, 2], inside


def reference_from_depth(views: Views, aabb: Tensor, resolution: int, depth: Sequence[Tensor] | None = None,
                         steps_per_cell: float = 2.0) -> tuple[Tensor, Tensor]:
    """(occupied, observed) boolean grids from depth maps along unit pixel rays (inf: no surface)."""
    depth = depth if depth is not None else views.depth
    if depth is None:
        raise ValueError("the reference occupancy needs depth maps: the scene has none and none were given")
    table = PixelTable(views)
    flat = torch.cat([d.reshape(-1) for d in depth]).double()
    occupied = torch.zeros(resolution**3, dtype=torch.bool)
    observed = torch.zeros(resolution**3, dtype=torch.bool)
    step = float((aabb[1] - aabb[0]).min()) / resolution / steps_per_cell
    for ids in torch.arange(len(flat)).split(CHUNK):
        rays = table.rays(ids, aabb)
        t_hit = flat[ids].to(rays.near.dtype)
        end = torch.minimum(rays.far, torch.where(torch.isfinite(t_hit), t_hit, rays.far))
        hit = torch.isfinite(t_hit) & (t_hit >= rays.near) & (t_hit <= rays.far)
        # A depth point lies on the boundary of the solid. Sampling a cell that holds only a sliver of solid
        # (a roof just above a cell face) would miss it even for the exact geometry, so the reference marks
        # the cell a quarter cell behind the visible surface, where the solid surely is.
        points = rays.origins[hit] + rays.directions[hit] * (t_hit[hit, None] + NUDGE * step)
        index, inside = cell_index(points, aabb, resolution)
        occupied[index[inside]] = True
        # Free space: cells the ray crossed before its surface (or through the whole box when it saw sky).
        count = ((end - rays.near) / step).clamp(min=0).floor().long()
        ray = torch.repeat_interleave(torch.arange(len(ids)), count)
        offset = torch.arange(len(ray)) - torch.repeat_interleave(count.cumsum(0) - count, count)
        t = rays.near[ray] + step * (offset.to(rays.near.dtype) + 0.5)
        free = rays.origins[ray] + rays.directions[ray] * t[:, None]
        index, inside = cell_index(free, aabb, resolution)
        observed[index[inside]] = True
    observed |= occupied
    shape = (resolution,) * 3
    return occupied.reshape(shape), observed.reshape(shape)


def predicted_grid(occupied: Callable[[Tensor], Tensor], aabb: Tensor, resolution: int,
                   subdivisions: int = 2) -> Tensor:
    """A cell is occupied when any of its subdivisions^3 sub-cell centres is: the predictor sampled into the
    grid, as in the paper. Sub-cells (not just the centre) keep thin surfaces from falling between samples."""
    axis = (torch.arange(resolution, dtype=torch.float32) + 0.5) / resolution
    centres = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    sub = ((torch.arange(subdivisions, dtype=torch.float32) + 0.5) / subdivisions - 0.5) / resolution
    offsets = torch.stack(torch.meshgrid(sub, sub, sub, indexing="ij"), -1).reshape(-1, 3)
    lo, size = aabb[0].float(), (aabb[1] - aabb[0]).float()
    result = torch.zeros(len(centres), dtype=torch.bool)
    for offset in offsets:
        result |= occupied(lo + (centres + offset) * size).cpu()
    return result.reshape((resolution,) * 3)


def evaluate_occupancy(occupied: Callable[[Tensor], Tensor], views: Views, aabb: Tensor, resolution: int = 64,
                       depth: list[Tensor] | None = None) -> dict[str, float]:
    """Accuracy, precision, recall, F1 over the cells the depth maps observe (see the module docstring)."""
    reference, observed = reference_from_depth(views, aabb, resolution, depth)
    predicted = predicted_grid(occupied, aabb, resolution)
    metrics = occupancy_metrics(predicted, reference, mask=observed)
    metrics["observed_fraction"] = float(observed.float().mean())
    metrics["resolution"] = resolution
    return metrics


def evaluate_occupancy_exact(occupied: Callable[[Tensor], Tensor], truth: OccupancyGrid, views: Views,
                             resolution: int = 64) -> dict[str, float]:
    """Against the scene's exact occupancy (synthetic scenes): on the cells the views' depth maps observe
    (the headline numbers, comparable with the depth protocol) and on the whole grid (`whole_grid_*`, which
    also counts building interiors and ground no camera sees)."""
    aabb = truth.aabb.float()
    # The truth sampled at the very points the predictor is, so a perfect predictor scores exactly 1.
    reference = predicted_grid(truth.lookup, aabb, resolution)
    _, observed = reference_from_depth(views, aabb, resolution)
    predicted = predicted_grid(occupied, aabb, resolution)
    metrics = occupancy_metrics(predicted, reference, mask=observed)
    whole = occupancy_metrics(predicted, reference)
    metrics.update({f"whole_grid_{k}": whole[k] for k in ("accuracy", "precision", "recall", "f1")})
    metrics["observed_fraction"] = float(observed.float().mean())
    metrics["resolution"] = resolution
    return metrics

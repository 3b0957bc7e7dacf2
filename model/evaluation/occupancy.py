"""The paper's occupancy protocol (section 4.1): a reference grid from depth maps, the predictor
sampled into the same grid, then accuracy / precision / recall / F1.

Real scenes have no ground truth, so the reference comes from depth maps (the paper uses a fully
trained vanilla Switch-NeRF's; a synthetic scene ships exact ones). Only the cells the depth maps
can speak for are compared: a cell holding a depth point is occupied, a cell some ray crossed before
its depth point is free, and cells no ray saw (inside buildings, behind walls) are left out, so
neither method is judged on them.

Beside the totals: recall by height layer (world z is up; the grid's z axis in 8 equal layers) and
of the ground (each column's lowest observed occupied cell), so a predictor that keeps roofs and
drops the ground (on an aerial city the largest surface) shows it; and other decision rules of the
same occupancy scored on the same reference."""

from __future__ import annotations

from typing import Any, Callable, Iterator, Mapping, Sequence

import torch
from torch import Tensor

from model.evaluation.metrics import occupancy_metrics
from model.scenes.rays import PixelTable
from model.scenes.scene import GroundTruthOccupancy, Views

CHUNK = 1 << 15  # rays per chunk while marking crossed cells
NUDGE = 0.5  # march steps (a quarter cell) behind the visible surface


def cell_index(points: Tensor, aabb: Tensor, resolution: int) -> tuple[Tensor, Tensor]:
    """Flat cell index of each point in a resolution^3 grid over aabb, and whether the point is
    inside."""
    u = (points - aabb[0]) / (aabb[1] - aabb[0])
    inside = ((u >= 0) & (u < 1)).all(-1)
    ijk = (u * resolution).long().clamp(0, resolution - 1)
    return (ijk[:, 0] * resolution + ijk[:, 1]) * resolution + ijk[:, 2], inside


def reference_from_depth(
    views: Views,
    aabb: Tensor,
    resolution: int,
    depth: Sequence[Tensor] | None = None,
    steps_per_cell: float = 2.0,
) -> tuple[Tensor, Tensor]:
    """(occupied, observed) boolean grids from depth maps along unit pixel rays (inf: no
    surface)."""
    depth = depth if depth is not None else views.depth
    if depth is None:
        raise ValueError(
            "the reference occupancy needs depth maps: the scene has none and none were given"
        )
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
        # A depth point lies on the boundary of the solid. Sampling a cell that holds only a sliver
        # of solid (a roof just above a cell face) would miss it even for the exact geometry, so the
        # reference marks the cell a quarter cell behind the visible surface, where the solid surely
        # is.
        points = rays.origins[hit] + rays.directions[hit] * (t_hit[hit, None] + NUDGE * step)
        index, inside = cell_index(points, aabb, resolution)
        occupied[index[inside]] = True
        # Free space: cells the ray crossed before its surface (or through the whole box when it saw
        # sky).
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


def subcell_points(aabb: Tensor, resolution: int, subdivisions: int = 2) -> Iterator[Tensor]:
    """For each of the subdivisions^3 sub-cell offsets, the (resolution^3, 3) world points at that
    offset in every cell of the grid over aabb (flat index order, i slowest)."""
    axis = (torch.arange(resolution, dtype=torch.float32) + 0.5) / resolution
    centres = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    sub = (
        (torch.arange(subdivisions, dtype=torch.float32) + 0.5) / subdivisions - 0.5
    ) / resolution
    offsets = torch.stack(torch.meshgrid(sub, sub, sub, indexing="ij"), -1).reshape(-1, 3)
    lo, size = aabb[0].float(), (aabb[1] - aabb[0]).float()
    for offset in offsets:
        yield lo + (centres + offset) * size


def predicted_grid(
    occupied: Callable[[Tensor], Tensor], aabb: Tensor, resolution: int, subdivisions: int = 2
) -> Tensor:
    """A cell is occupied when any of its subdivisions^3 sub-cell centres is: the predictor sampled
    into the grid, as in the paper. Sub-cells (not just the centre) keep thin surfaces from falling
    between samples."""
    result = torch.zeros(resolution**3, dtype=torch.bool)
    for points in subcell_points(aabb, resolution, subdivisions):
        result |= occupied(points).cpu()
    return result.reshape((resolution,) * 3)


LAYERS = 8  # height layers of the evaluation grid's z axis (world z is up): 8 cells each at 64^3
Rules = Mapping[str, Callable[[Tensor], Tensor]]  # other decisions of the same occupancy, by name
# what each decision rule reports, prefixed
RULE_KEYS = ("recall", "precision", "f1", "ground_recall")


def layer_bounds(resolution: int, layers: int = LAYERS) -> list[tuple[int, int]]:
    """[start, end) z cells of each height layer; equal when the resolution divides evenly."""
    cuts = [round(i * resolution / layers) for i in range(layers + 1)]
    return list(zip(cuts[:-1], cuts[1:]))


def recall_by_layer(predicted: Tensor, reference: Tensor, observed: Tensor) -> list[dict[str, Any]]:
    """Per height layer (bottom first): the occupied-and-observed reference cells, how many of them
    the predictor keeps, the recall (None without reference cells) and the layer's z range in the
    box's [0, 1]. A sampler that drops the ground or the roofs loses recall in one layer while the
    total can still look fine."""
    resolution = reference.shape[2]
    target = reference & observed
    rows = []
    for lo, hi in layer_bounds(resolution):
        cells = int(target[:, :, lo:hi].sum())
        found = int((target & predicted)[:, :, lo:hi].sum())
        rows.append(
            {
                "z_min": lo / resolution,
                "z_max": hi / resolution,
                "reference_cells": cells,
                "predicted_cells": found,
                "recall": found / cells if cells else None,
            }
        )
    return rows


def ground_cells(reference: Tensor, observed: Tensor) -> Tensor:
    """(X, Y, Z) bool: in each (x, y) column the lowest occupied cell among the observed ones. On an
    aerial city that is the ground wherever the ground shows; in a column a roof hides from every
    view it is the roof, the lowest surface any view can speak for (so the exact and the depth
    protocols mark the same cells)."""
    target = reference & observed
    z = torch.arange(target.shape[2], device=target.device)
    # Z where the column has none
    lowest = torch.where(target, z, target.shape[2]).min(dim=2).values
    return target & (z == lowest[..., None])


def ground_recall(predicted: Tensor, reference: Tensor, observed: Tensor) -> dict[str, Any]:
    ground = ground_cells(reference, observed)
    cells = int(ground.sum())
    return {
        "ground_recall": int((ground & predicted).sum()) / cells if cells else None,
        "ground_cells": cells,
    }


def score_grid(predicted: Tensor, reference: Tensor, observed: Tensor) -> dict[str, Any]:
    """occupancy_metrics on the observed cells, with the recall by height layer and of the
    ground."""
    metrics: dict[str, Any] = dict(occupancy_metrics(predicted, reference, mask=observed))
    metrics.update(ground_recall(predicted, reference, observed))
    metrics["layers"] = recall_by_layer(predicted, reference, observed)
    return metrics


def score_rules(
    rules: Rules | None, reference: Tensor, observed: Tensor, aabb: Tensor, resolution: int
) -> dict[str, Any]:
    """Each named decision rule scored against the reference already computed (the slow part is not
    repeated), its keys prefixed by its name: `top1_recall`, `top1_f1`, `top1_ground_recall`, ..."""
    out: dict[str, Any] = {}
    for name, rule in (rules or {}).items():
        scores = score_grid(predicted_grid(rule, aabb, resolution), reference, observed)
        out.update({f"{name}_{key}": scores[key] for key in RULE_KEYS})
    return out


def evaluate_occupancy(
    occupied: Callable[[Tensor], Tensor],
    views: Views,
    aabb: Tensor,
    resolution: int = 64,
    depth: list[Tensor] | None = None,
    rules: Rules | None = None,
) -> dict[str, Any]:
    """Accuracy, precision, recall, F1 over the cells the depth maps observe (see the module
    docstring), by height layer (`layers`) and of the ground (`ground_recall`); `rules`: other
    decisions scored alike."""
    reference, observed = reference_from_depth(views, aabb, resolution, depth)
    predicted = predicted_grid(occupied, aabb, resolution)
    metrics = score_grid(predicted, reference, observed)
    metrics.update(score_rules(rules, reference, observed, aabb, resolution))
    metrics["observed_fraction"] = float(observed.float().mean())
    metrics["resolution"] = resolution
    return metrics


def evaluate_occupancy_exact(
    occupied: Callable[[Tensor], Tensor],
    truth: GroundTruthOccupancy,
    views: Views,
    resolution: int = 64,
    rules: Rules | None = None,
) -> dict[str, Any]:
    """Against the scene's exact occupancy (synthetic scenes): on the cells the views' depth maps
    observe (the headline numbers, comparable with the depth protocol, by height layer and of the
    ground as there) and on the whole grid (`whole_grid_*`, which also counts building interiors and
    ground no camera sees)."""
    aabb = truth.aabb.float()
    # The truth sampled at the very points the predictor is, so a perfect predictor scores exactly
    # 1.
    reference = predicted_grid(truth.lookup, aabb, resolution)
    _, observed = reference_from_depth(views, aabb, resolution)
    predicted = predicted_grid(occupied, aabb, resolution)
    metrics = score_grid(predicted, reference, observed)
    whole = occupancy_metrics(predicted, reference)
    metrics.update({f"whole_grid_{k}": whole[k] for k in ("accuracy", "precision", "recall", "f1")})
    metrics.update(score_rules(rules, reference, observed, aabb, resolution))
    metrics["observed_fraction"] = float(observed.float().mean())
    metrics["resolution"] = resolution
    return metrics

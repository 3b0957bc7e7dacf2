"""What reaches the main network, counted the same way for every method (the paper's occupancy ratio
is "the points that go through the main network").

Each ray's foreground segment [near, far] is cut into `bins` equal coarse bins (LeCO's own coarse
bins; the other methods are counted on the same bins). A bin *reaches* the main network when at
least one main-network sample lies in it, whatever put it there: O's decision, dilation, a fallback,
a proposal or a grid cell. Only rays that cross the foreground box count (a ray that misses it has
no bin to keep), so a method is not flattered by sky."""

from __future__ import annotations

import torch
from torch import Tensor

from model.render.samples import PackedSamples


def sample_bins(samples: PackedSamples, near: Tensor, far: Tensor, bins: int) -> Tensor:
    """The coarse bin (0 .. bins - 1) of each sample's mid-point along its ray."""
    i = samples.ray_index
    span = (far - near).clamp(min=1e-12)[i]
    return ((samples.mids - near[i]) / span * bins).floor().long().clamp(0, bins - 1)


def reached_bins(samples: PackedSamples, near: Tensor, far: Tensor, bins: int) -> Tensor:
    """(R, bins) bool: the coarse bins that hold at least one main-network sample (rays that miss
    the box: none)."""
    reached = torch.zeros(len(near) * bins, dtype=torch.bool, device=near.device)
    if len(samples):
        reached[samples.ray_index * bins + sample_bins(samples, near, far, bins)] = True
    return reached.reshape(len(near), bins) & (far > near)[:, None]


def step_accounting(
    samples: PackedSamples, near: Tensor, far: Tensor, bins: int
) -> dict[str, Tensor]:
    """Per-step figures, as 0-dim tensors (read when logged, model/methods/parts.py): the share of
    the hit rays' coarse bins that reach the main network (`occupancy_ratio`), main samples per hit
    ray, and the share of rays that hit the box. All three are 0 when no ray hits the box."""
    hit = far > near
    hits = hit.sum()
    per_hit = hits.clamp(min=1)  # no ray hits: every share below reads 0
    reached = reached_bins(samples, near, far, bins)
    return {
        "occupancy_ratio": reached.sum() / (per_hit * bins),
        # a tensor over a tensor: `int / tensor` multiplies by the reciprocal, off by a rounding
        "samples_per_hit_ray": torch.where(
            hits > 0, hits.new_full((), len(samples)) / per_hit, 0.0
        ),
        "hit_ray_fraction": hits / max(len(near), 1),
    }


def surface_accounting(
    samples: PackedSamples, weights: Tensor, near: Tensor, far: Tensor, depth: Tensor, bins: int
) -> dict[str, Tensor]:
    """Per surface ray (a finite depth inside [near, far)): whether the bin holding the visible
    surface reaches the main network, and the foreground's opacity (summed render weights of the
    main samples).

    Returns `surface` (R,) bool, `kept` (R,) bool and `opacity` (R,) float, to be summed over many
    batches."""
    surface = torch.isfinite(depth) & (depth >= near) & (depth < far) & (far > near)
    reached = reached_bins(samples, near, far, bins)
    span = (far - near).clamp(min=1e-12)
    safe = torch.where(surface, depth, near)
    surface_bin = ((safe - near) / span * bins).floor().long().clamp(0, bins - 1)
    kept = reached.gather(1, surface_bin[:, None])[:, 0] & surface
    opacity = torch.zeros(len(near), dtype=weights.dtype, device=weights.device)
    if len(samples):
        opacity = opacity.index_add(0, samples.ray_index, weights.detach())
    return {"surface": surface, "kept": kept, "opacity": opacity}

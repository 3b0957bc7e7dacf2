"""O keeps learning during the main phase (the paper freezes O after phase 1).

The main network's rendering weights (detached) say, for every coarse bin the guided sampler kept,
whether the bin holds what the ray sees. Two signals, in the spirit of a proposal network's
interlevel loss:
- a bin that carries at least `surface_weight` of its ray's weight is occupied: O is pushed to keep
  it;
- a kept bin that carries less, on a ray that still sees past it (transmittance after the bin above
  `seen_through`), is free space this view looked through: O is pushed to drop it.
Bins the sampler skipped, and bins hidden behind what the ray already hit, teach nothing: the first
because the main network never looked there, the second because another view may see a surface
there. Dilation, jittered queries, the fallback and the explored bins (guided.explore_bins) keep
showing the main network bins O does not yet keep, so a surface O missed in phase 1 can be found
and learned.

A bin's label speaks for the whole bin but O is asked at one point of it, so a thin surface (a
tree's crown, a silo's top) that fills a sliver of a long bin is taught "keep" at points of empty
air, and "drop" there by every ray that grazes past: O smooths it away. With `surface_points`, O is
also taught to keep the very point each ray shows most (its main sample of largest weight, on rays
whose foreground is opaque), where the surface is."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from model.estimators.occupancy import OccupancyQuery
from model.estimators.placement import bin_mass
from model.fields.hmoe import OccupancyNetwork
from model.render.accounting import reached_bins
from model.render.samples import PackedSamples
from model.scenes.rays import RayBatch

# surface_points: a ray teaches O where its surface is only when its foreground shows more than
# the background does (a ray into the sky has no surface to teach)
SHOWN_OPACITY = 0.5


class OnlineOccupancy(OccupancyQuery):
    """The guided sampler's `occupied` with O's logits kept (with gradient) for `loss` after the
    render."""

    def __init__(
        self,
        network: OccupancyNetwork,
        empty_threshold: float | None,
        surface_weight: float = 0.05,
        seen_through: float = 0.5,
        free_opacity: float = 0.0,
        surface_points: bool = False,
    ):
        super().__init__(network, empty_threshold)
        self.learn = True
        self.surface_weight, self.seen_through, self.free_opacity = (
            surface_weight,
            seen_through,
            free_opacity,
        )
        self.surface_points = surface_points

    def bin_targets(
        self, samples: PackedSamples, weights: Tensor, rays: RayBatch, num_coarse: int
    ) -> tuple[Tensor, Tensor]:
        """(R, n) target (1 occupied, 0 free) and mask (bins that teach) from the packed render
        weights."""
        mass = bin_mass(samples, weights, rays.near, rays.far, num_coarse)
        sampled = reached_bins(samples, rays.near, rays.far, num_coarse)
        # transmittance left after each bin (skipped bins hold no mass)
        after = 1.0 - mass.cumsum(dim=1)
        surface = mass >= self.surface_weight
        free = sampled & ~surface & (after > self.seen_through)
        # a semi-transparent foreground leaves the rest to the background: no "free"
        if self.free_opacity > 0:
            free &= mass.sum(dim=1, keepdim=True) >= self.free_opacity
        return surface.to(weights.dtype), surface | free

    def decision_logit(self, logits: Tensor) -> Tensor:
        """A logit that is positive exactly where the sampler keeps the point
        (OccupancyNetwork.decision_logit)."""
        return self.network.decision_logit(logits, self.empty_threshold)

    def loss(
        self, samples: PackedSamples, weights: Tensor, rays: RayBatch, num_coarse: int
    ) -> Tensor:
        """Binary cross-entropy on the decision logit, over the bins that teach: O keeps a point
        where most rays through its bin found a surface there, whatever the threshold the sampler
        decides with."""
        target, mask = self.bin_targets(samples, weights, rays, num_coarse)
        if self.logits is None:
            raise RuntimeError(
                "OnlineOccupancy.loss needs the logits of this step's occupied() call"
            )
        # O was asked at one or more points per bin and keeps the bin when any is kept: the bin's
        # logit is their max
        logit = self.decision_logit(self.logits).reshape(*target.shape, -1).amax(dim=-1)
        nll = F.binary_cross_entropy_with_logits(logit, target, reduction="none")
        self.logits = None
        loss = (nll * mask).sum() / mask.sum().clamp(min=1)
        if self.surface_points:
            loss = loss + self.point_loss(samples, weights, rays)
        return loss

    def shown_points(self, samples: PackedSamples, weights: Tensor, rays: RayBatch) -> Tensor:
        """(P, 3): on each ray whose foreground opacity reaches SHOWN_OPACITY, the mid-point
        of its main sample of largest weight (ties keep every tied sample)."""
        weights = weights.detach().reshape(-1)
        count = len(rays.origins)
        best = torch.zeros(count, dtype=weights.dtype, device=weights.device)
        best = best.scatter_reduce(0, samples.ray_index, weights, "amax", include_self=True)
        opacity = torch.zeros_like(best).index_add_(0, samples.ray_index, weights)
        ray = samples.ray_index
        shown = (weights == best[ray]) & (weights > 0) & (opacity[ray] >= SHOWN_OPACITY)
        rows = ray[shown]
        return rays.origins[rows] + rays.directions[rows] * samples.mids[shown, None]

    def point_loss(self, samples: PackedSamples, weights: Tensor, rays: RayBatch) -> Tensor:
        """Binary cross-entropy pushing O to keep the points the rays show (`shown_points`)."""
        points = self.shown_points(samples, weights, rays)
        if not len(points):
            return weights.sum() * 0.0
        logits, _ = self.network.query(points)
        logit = self.decision_logit(logits)
        return F.binary_cross_entropy_with_logits(logit, torch.ones_like(logit))

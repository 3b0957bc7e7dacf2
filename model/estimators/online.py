"""O keeps learning during the main phase (the paper freezes O after phase 1).

The main network's rendering weights (detached) say, for every coarse bin the guided sampler kept,
whether the bin holds what the ray sees. Two signals, in the spirit of a proposal network's
interlevel loss:
- a bin that carries at least `surface_weight` of its ray's weight is occupied: O is pushed to keep
  it;
- a kept bin that carries less, on a ray that still sees past it (transmittance after the bin above
  `seen_through`), is free space this view looked through: O is pushed to drop it.
With `free_error`, a kept bin is labelled free only on rays the field already renders well
(squared colour error at most `free_error`): a ray that paints the ground through a roof's top the
field has not fitted yet would teach O to drop the top.
Bins the sampler skipped, and bins hidden behind what the ray already hit, teach nothing: the first
because the main network never looked there, the second because another view may see a surface
there. Dilation, jittered queries, the fallback and the explored bins (guided.explore_bins) keep
showing the main network bins O does not yet keep, so a surface O missed in phase 1 can be found
and learned.

A bin's label speaks for the whole bin but O is asked at one point of it, so a thin surface (a
tree's crown, a silo's top) that fills a sliver of a long bin is taught "keep" at points of empty
air, and "drop" there by every ray that grazes past: O smooths it away. With `surface_points`, O is
also taught to keep the very point each ray shows most (its main sample of largest weight, on rays
whose foreground is opaque), where the surface is. A ray that grazes a crown's top on its way to
the ground shows the ground most, so the top is taught only through its bin, at a random point of
it. With `dense_points`, O is taught to keep every main sample that stops at least
`surface_weight` of the light reaching it while the ray still sees (at least `seen_through` of its
light gets there), each at its own point. (O can hold such tops: fitted straight to the exact
occupancy it keeps every height layer, bench/occupancy_capacity.py; what it lacks in a run is the
labels.)

With `box_points`, O is also taught at points drawn uniformly over the scene's box, each labelled
by the main field's own density there (occupied where its alpha over one step of the box diagonal
/ BOX_STEPS reaches `box_alpha`): the labels reach the whole box, not only where the sampler sent
main samples, as Instant-NGP's grid is updated from the field's density at random cells."""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from model.estimators.occupancy import OccupancyQuery
from model.estimators.placement import bin_mass
from model.fields.hmoe import OccupancyNetwork
from model.render.accounting import reached_bins
from model.render.noise import Noise
from model.render.samples import PackedSamples
from model.render.volume import exclusive_cumsum_per_ray
from model.scenes.rays import RayBatch

# the main field's density at world points (N, 3) -> (N,)
FieldAt = Callable[[Tensor], Tensor]

# box_points: the step a point's alpha is taken over is the box diagonal over this many (the `cpu`
# profile's grid marches 256)
BOX_STEPS = 256

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
        free_error: float = 0.0,
        surface_points: bool = False,
        dense_points: bool = False,
        box: Tensor | None = None,
        box_points: int = 0,
        box_alpha: float = 0.01,
    ):
        """`box`: (2, 3) the scene's box, where `box_points` are drawn."""
        super().__init__(network, empty_threshold)
        self.learn = True
        self.surface_weight, self.seen_through, self.free_opacity = (
            surface_weight,
            seen_through,
            free_opacity,
        )
        self.free_error = free_error
        self.surface_points, self.dense_points = surface_points, dense_points
        if box_points and box is None:
            raise ValueError("OnlineOccupancy: box_points needs the scene's box")
        self.box, self.box_points, self.box_alpha = box, box_points, box_alpha

    def bin_targets(
        self,
        samples: PackedSamples,
        weights: Tensor,
        rays: RayBatch,
        num_coarse: int,
        rgb: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        """(R, n) target (1 occupied, 0 free) and mask (bins that teach) from the packed render
        weights; `rgb` (R, 3): the rays' rendered colours (needed with `free_error`)."""
        mass = bin_mass(samples, weights, rays.near, rays.far, num_coarse)
        sampled = reached_bins(samples, rays.near, rays.far, num_coarse)
        # transmittance left after each bin (skipped bins hold no mass)
        after = 1.0 - mass.cumsum(dim=1)
        surface = mass >= self.surface_weight
        free = sampled & ~surface & (after > self.seen_through)
        # a semi-transparent foreground leaves the rest to the background: no "free"
        if self.free_opacity > 0:
            free &= mass.sum(dim=1, keepdim=True) >= self.free_opacity
        # a ray the field still renders wrong may pass a surface the field has not fitted yet: it
        # does not teach O to drop what it passes
        if self.free_error > 0:
            if rgb is None:
                raise ValueError("OnlineOccupancy: free_error needs the rays' rendered colours")
            error = (rgb.detach() - rays.rgb).square().mean(dim=-1, keepdim=True)
            free &= error <= self.free_error
        return surface.to(weights.dtype), surface | free

    def decision_logit(self, logits: Tensor) -> Tensor:
        """A logit that is positive exactly where the sampler keeps the point
        (OccupancyNetwork.decision_logit)."""
        return self.network.decision_logit(logits, self.empty_threshold)

    def loss(
        self,
        samples: PackedSamples,
        weights: Tensor,
        rays: RayBatch,
        num_coarse: int,
        rgb: Tensor | None = None,
    ) -> Tensor:
        """Binary cross-entropy on the decision logit, over the bins that teach: O keeps a point
        where most rays through its bin found a surface there, whatever the threshold the sampler
        decides with."""
        target, mask = self.bin_targets(samples, weights, rays, num_coarse, rgb)
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
        if self.surface_points or self.dense_points:
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

    def matter_points(self, samples: PackedSamples, weights: Tensor, rays: RayBatch) -> Tensor:
        """(P, 3): the mid-points of the main samples that stop at least `surface_weight` of the
        light reaching them (alpha_i = w_i / T_i) where at least `seen_through` of the ray's light
        still gets there (T_i = 1 - the weight in front); a point behind what the ray already hit
        teaches nothing (another view may see it empty)."""
        weights = weights.detach().reshape(-1)
        reach = 1.0 - exclusive_cumsum_per_ray(weights, samples.ray_index, len(rays.origins))
        alpha = weights / reach.clamp(min=1e-6)
        dense = (weights > 0) & (alpha >= self.surface_weight) & (reach >= self.seen_through)
        rows = samples.ray_index[dense]
        return rays.origins[rows] + rays.directions[rows] * samples.mids[dense, None]

    def point_loss(self, samples: PackedSamples, weights: Tensor, rays: RayBatch) -> Tensor:
        """Binary cross-entropy pushing O to keep the points the rays show (`shown_points`) and,
        with `dense_points`, every point the field holds matter at (`matter_points`)."""
        parts = []
        if self.surface_points:
            parts.append(self.shown_points(samples, weights, rays))
        if self.dense_points:
            parts.append(self.matter_points(samples, weights, rays))
        points = torch.cat(parts)
        if not len(points):
            return weights.sum() * 0.0
        logits, _ = self.network.query(points)
        logit = self.decision_logit(logits)
        return F.binary_cross_entropy_with_logits(logit, torch.ones_like(logit))

    def box_targets(self, field: FieldAt, noise: Noise | None) -> tuple[Tensor, Tensor]:
        """(P, 3) points drawn uniformly over the box and (P,) their labels: 1 where the field's
        alpha over one step of the box diagonal / BOX_STEPS reaches `box_alpha`, asked without
        gradient and without the field's training noise."""
        assert self.box is not None
        lo, hi = self.box[0], self.box[1]
        shape = (self.box_points, 3)
        u = (noise or Noise()).rand(*shape, device=lo.device, dtype=lo.dtype)
        points = lo + u * (hi - lo)
        step = (hi - lo).norm() / BOX_STEPS
        with torch.no_grad():
            sigma = field(points).float()
        # alpha = 1 - exp(-sigma * step) >= a  <=>  sigma * step >= -log(1 - a)
        bound = -torch.log1p(torch.tensor(-self.box_alpha, device=sigma.device))
        return points, (sigma * step >= bound).to(points.dtype)

    def box_loss(self, field: FieldAt, noise: Noise | None) -> Tensor:
        """Binary cross-entropy on O's decision logit at `box_points` points of the box, against
        the field's own occupancy there (`box_targets`)."""
        points, target = self.box_targets(field, noise)
        logits, _ = self.network.query(points)
        return F.binary_cross_entropy_with_logits(self.decision_logit(logits), target)

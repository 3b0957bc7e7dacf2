"""O's second placement pass (guided.placement_fine): the coarse histogram places M intermediate
intervals over the kept bins, O's placement head is asked at their mid-points, and the main
network's samples are drawn from that finer histogram. It is the second level of a proposal sampler
(mip-NeRF 360), with O's one head for both levels: inside a kept coarse bin the samples are no
longer spread evenly, they follow where O expects the surface. Both levels learn from the interlevel
bound against the main network's detached weights (eq. 13).

Everything happens on the kept bins laid end to end (the coordinate s of
model/estimators/placement.py): no interval straddles a dropped bin, and an interval's length in s
is its length along the ray."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from model.estimators.proposal import interlevel_loss, pdf_edges
from model.render.noise import Noise
from model.render.samples import PackedSamples
from model.render.volume import batched_weights


def kept_axis(edges: Tensor, keep: Tensor) -> Tensor:
    """(R, B + 1) the coarse bins' edges in s: kept bins end to end, dropped ones zero-long."""
    width = (edges[:, 1:] - edges[:, :-1]) * keep
    return torch.cat([torch.zeros_like(width[:, :1]), width.cumsum(-1)], -1)


def to_t(s: Tensor, s_edges: Tensor, edges: Tensor) -> Tensor:
    """Positions s (R, K) on the kept axis back to t along the ray. Ties go to the last bin starting
    at that s, which is the kept one (a dropped bin is zero-long, so the kept bin after it starts at
    the same s)."""
    b = edges.shape[1] - 1
    bin_ = (torch.searchsorted(s_edges.contiguous(), s.contiguous(), right=True) - 1).clamp(
        0, b - 1
    )
    return edges.gather(1, bin_) + (s - s_edges.gather(1, bin_))


@dataclass
class FineDraw:
    """What the loss needs from one draw: the rows (of the hit rays) drawn, the intermediate
    intervals' edges in s and their mid-points in t, and the main samples' edges in s (exactly n per
    row)."""

    rows: Tensor
    s_edges: Tensor
    coarse: Tensor  # (R, M + 1) intermediate edges in s
    t_mid: Tensor  # (R, M) their mid-points along the ray
    main: Tensor  # (R, n + 1) the main samples' edges in s
    # (R, M) O's densities at t_mid, as `density` returned them (with gradient while O learns)
    sigma: Tensor


def fine_samples(
    rows: Tensor,
    edges: Tensor,
    keep: Tensor,
    weights: Tensor,
    intermediate: int,
    n: int,
    density: Callable[[Tensor], Tensor],
    noise: Noise | None,
    anneal: float,
    padding: float,
) -> tuple[PackedSamples, FineDraw]:
    """Exactly n samples per row of `edges` (R, B + 1) inside its kept bins (`rows`: which hit rays
    those are, kept for the loss), drawn in two levels: `intermediate` intervals by the coarse
    histogram `weights` (R, B) (padding added), then n by O's densities at their mid-points
    (`density`: (R, M) t -> (R, M) sigma; the draw uses it detached, and keeps it for the loss, so a
    step where O learns asks O once)."""
    s_edges = kept_axis(edges, keep)
    mass = weights.clamp(min=0) * keep
    # no weight: by bin
    mass = torch.where(mass.sum(-1, keepdim=True) > 0, mass, keep.to(mass.dtype))
    coarse = pdf_edges(s_edges, mass, intermediate, noise, padding=0.0)
    t_mid = to_t(0.5 * (coarse[:, 1:] + coarse[:, :-1]), s_edges, edges)
    sigma = density(t_mid)
    fine = batched_weights(sigma.detach().double(), (coarse[:, 1:] - coarse[:, :-1]).double())[
        0
    ].to(coarse.dtype)
    main = pdf_edges(coarse, fine, n, noise, anneal=anneal, padding=padding)
    mid, delta = 0.5 * (main[:, 1:] + main[:, :-1]), main[:, 1:] - main[:, :-1]
    t = to_t(mid, s_edges, edges).reshape(-1)
    delta = delta.reshape(-1)
    ray = torch.arange(len(edges), device=edges.device).repeat_interleave(n)
    return PackedSamples(t - 0.5 * delta, t + 0.5 * delta, ray), FineDraw(
        rows, s_edges, coarse, t_mid, main, sigma
    )


def fine_placement_loss(draw: FineDraw, sigma: Tensor, main_weights: Tensor) -> Tensor:
    """The interlevel bound on the intermediate level: O's densities `sigma` (R, M) at the
    intermediate mid-points (with gradient), composited over the intermediate intervals, must bound
    the main network's detached weights (R, n) on its own intervals."""
    proposal = batched_weights(sigma, (draw.coarse[:, 1:] - draw.coarse[:, :-1]).to(sigma.dtype))[0]
    return interlevel_loss(draw.main, main_weights, [(draw.coarse, proposal)])

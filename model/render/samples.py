"""Samples along rays as intervals [start, end) inside each ray's foreground segment [near, far].

- stratified: n equal bins with one jittered interval each (coarse);
- inverse-CDF: n more intervals drawn from coarse weights (fine); merged with the coarse ones;
- split: kept bins cut into k stratified sub-intervals, returned packed (flat samples + ray index);
  LeCO's guided sampler (model/estimators/guided.py) decides which bins are kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from model.render.noise import Noise


@dataclass
class PackedSamples:
    starts: Tensor  # (S,)
    ends: Tensor  # (S,)
    ray_index: Tensor  # (S,) int64, grouped by ray, increasing along each ray

    @property
    def mids(self) -> Tensor:
        return 0.5 * (self.starts + self.ends)

    @property
    def deltas(self) -> Tensor:
        return self.ends - self.starts

    def __len__(self) -> int:
        return len(self.starts)

    def subset(self, keep: Tensor) -> "PackedSamples":
        """The samples where keep is true, in the same order (so still grouped by ray, increasing
        t)."""
        return PackedSamples(self.starts[keep], self.ends[keep], self.ray_index[keep])


def stratified_edges(near: Tensor, far: Tensor, n: int, noise: Noise | None) -> Tensor:
    """(R, n + 1) bin edges; with noise the inner edges are jittered inside their bins
    (training)."""
    u = torch.linspace(0.0, 1.0, n + 1, device=near.device)
    if noise is not None:
        jitter = (noise.rand(len(near), n - 1, device=near.device) - 0.5) / n
        u = u.expand(len(near), n + 1).clone()
        u[:, 1:-1] += jitter
    return near[:, None] + (far - near)[:, None] * u


def inverse_cdf_edges(edges: Tensor, weights: Tensor, n: int, noise: Noise | None) -> Tensor:
    """(R, n) new sample positions distributed like the coarse weights (piecewise-constant pdf)."""
    pdf = weights.detach() + 1e-5  # keep every bin reachable and empty rays uniform
    cdf = torch.cat(
        [torch.zeros_like(pdf[:, :1]), (pdf / pdf.sum(-1, keepdim=True)).cumsum(-1)], -1
    )
    if noise is None:
        u = (
            torch.linspace(0.0, 1.0, n + 2, device=edges.device)[1:-1]
            .expand(len(edges), n)
            .contiguous()
        )
    else:
        u = noise.rand(len(edges), n, device=edges.device)
    return invert_cdf(edges, cdf, u)


def invert_cdf(edges: Tensor, cdf: Tensor, u: Tensor) -> Tensor:
    """(R, K) positions t whose CDF is u, the CDF (R, M + 1) being linear inside each bin of `edges`
    (R, M + 1)."""
    hi = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[-1] - 1)
    lo = hi - 1
    c0, c1 = cdf.gather(-1, lo), cdf.gather(-1, hi)
    e0, e1 = edges.gather(-1, lo), edges.gather(-1, hi)
    frac = ((u - c0) / (c1 - c0).clamp(min=1e-12)).clamp(0, 1)
    return e0 + frac * (e1 - e0)


def merge_edges(coarse_edges: Tensor, fine_points: Tensor) -> Tensor:
    """Sorted union of coarse edges and fine points: (R, n_coarse + 1 + n_fine) edges, all
    composited together."""
    return torch.sort(torch.cat([coarse_edges, fine_points.detach()], -1), dim=-1).values


def pack_edges(edges: Tensor) -> PackedSamples:
    """Batched (R, N + 1) edges -> packed intervals (zero-length ones included)."""
    r, m = edges.shape
    return PackedSamples(
        edges[:, :-1].reshape(-1),
        edges[:, 1:].reshape(-1),
        torch.arange(r, device=edges.device).repeat_interleave(m - 1),
    )


def split_bins(
    lo: Tensor, hi: Tensor, ray: Tensor, counts: Tensor, noise: Noise | None
) -> PackedSamples:
    """Bin k of [lo_k, hi_k) split into counts_k stratified sub-intervals (inner edges jittered with
    noise); bins must come grouped by ray in increasing t, and so do the samples."""
    bin_of = torch.repeat_interleave(torch.arange(len(lo), device=lo.device), counts)
    first = torch.cumsum(counts, 0) - counts
    # sub-interval index inside its bin
    j = torch.arange(len(bin_of), device=lo.device) - first[bin_of]
    c, width = counts[bin_of].to(lo.dtype), (hi - lo)[bin_of]
    shift = torch.zeros_like(c)
    if noise is not None:
        shift = noise.rand(len(c), device=lo.device, dtype=lo.dtype) - 0.5
        # the bin's own start edge stays put
        shift = torch.where(j > 0, shift, torch.zeros_like(shift))
    starts = lo[bin_of] + width * (j + shift) / c
    last = j == counts[bin_of] - 1
    ends = torch.where(last, hi[bin_of], torch.roll(starts, -1))
    return PackedSamples(starts, ends, ray[bin_of])

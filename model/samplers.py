"""Samples along rays as intervals [start, end) inside each ray's foreground segment [near, far].

- stratified: n equal bins with one jittered interval each (coarse);
- inverse-CDF: n more intervals drawn from coarse weights (fine); merged with the coarse ones;
- guided (LeCO, section 3.4): coarse bins -> occupancy predictor -> drop unoccupied -> split each kept bin into
  k stratified sub-intervals, returned packed (flat samples + ray index).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor


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


def stratified_edges(near: Tensor, far: Tensor, n: int, generator: torch.Generator | None) -> Tensor:
    """(R, n + 1) bin edges; with a generator the inner edges are jittered inside their bins (training)."""
    u = torch.linspace(0.0, 1.0, n + 1, device=near.device)
    if generator is not None:
        jitter = (torch.rand(len(near), n - 1, generator=generator, device=near.device) - 0.5) / n
        u = u.expand(len(near), n + 1).clone()
        u[:, 1:-1] += jitter
    return near[:, None] + (far - near)[:, None] * u


def inverse_cdf_edges(edges: Tensor, weights: Tensor, n: int, generator: torch.Generator | None) -> Tensor:
    """(R, n) new sample positions distributed like the coarse weights (piecewise-constant pdf)."""
    pdf = weights.detach() + 1e-5  # keep every bin reachable and empty rays uniform
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), (pdf / pdf.sum(-1, keepdim=True)).cumsum(-1)], -1)
    if generator is None:
        u = torch.linspace(0.0, 1.0, n + 2, device=edges.device)[1:-1].expand(len(edges), n).contiguous()
    else:
        u = torch.rand(len(edges), n, generator=generator, device=edges.device)
    hi = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[-1] - 1)
    lo = hi - 1
    c0, c1 = cdf.gather(-1, lo), cdf.gather(-1, hi)
    e0, e1 = edges.gather(-1, lo), edges.gather(-1, hi)
    frac = ((u - c0) / (c1 - c0).clamp(min=1e-12)).clamp(0, 1)
    return e0 + frac * (e1 - e0)


def merge_edges(coarse_edges: Tensor, fine_points: Tensor) -> Tensor:
    """Sorted union of coarse edges and fine points: (R, n_coarse + 1 + n_fine) edges, all composited together."""
    return torch.sort(torch.cat([coarse_edges, fine_points.detach()], -1), dim=-1).values


def pack_edges(edges: Tensor) -> PackedSamples:
    """Batched (R, N + 1) edges -> packed intervals (zero-length ones included)."""
    r, m = edges.shape
    return PackedSamples(edges[:, :-1].reshape(-1), edges[:, 1:].reshape(-1),
                         torch.arange(r, device=edges.device).repeat_interleave(m - 1))


def guided_samples(
    near: Tensor, far: Tensor, origins: Tensor, directions: Tensor, occupied: Callable[[Tensor], Tensor],
    num_coarse: int, split: int, generator: torch.Generator | None,
) -> tuple[PackedSamples, Tensor]:
    """LeCO guided sampling; returns the packed fine samples and the kept fraction of coarse samples
    (the occupancy ratio). Rays with nothing occupied get no samples and render the background."""
    edges = stratified_edges(near, far, num_coarse, None)  # coarse bins are fixed; jitter happens inside them
    mids = 0.5 * (edges[:, :-1] + edges[:, 1:])
    points = origins[:, None, :] + directions[:, None, :] * mids[..., None]
    keep = occupied(points.reshape(-1, 3)).reshape(mids.shape) & (far > near)[:, None]
    ray, bin_ = torch.nonzero(keep, as_tuple=True)  # row-major: grouped by ray, increasing t
    lo, hi = edges[ray, bin_], edges[ray, bin_ + 1]
    u = torch.arange(split + 1, device=near.device, dtype=near.dtype) / split
    sub = lo[:, None] + (hi - lo)[:, None] * u  # (K, split + 1) sub-edges
    if generator is not None and split > 1:
        sub[:, 1:-1] += (torch.rand(len(lo), split - 1, generator=generator, device=near.device) - 0.5) * ((hi - lo) / split)[:, None]
    samples = PackedSamples(sub[:, :-1].reshape(-1), sub[:, 1:].reshape(-1), ray.repeat_interleave(split))
    return samples, keep.float().mean()

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

    def subset(self, keep: Tensor) -> "PackedSamples":
        """The samples where keep is true, in the same order (so still grouped by ray, increasing t)."""
        return PackedSamples(self.starts[keep], self.ends[keep], self.ray_index[keep])


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
    return invert_cdf(edges, cdf, u)


def invert_cdf(edges: Tensor, cdf: Tensor, u: Tensor) -> Tensor:
    """(R, K) positions t whose CDF is u, the CDF (R, M + 1) being linear inside each bin of `edges` (R, M + 1)."""
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


def dilate_bins(keep: Tensor, radius: int) -> Tensor:
    """Also keep every bin within `radius` bins of a kept one along its ray (a 1-D max filter)."""
    if radius == 0 or keep.shape[1] == 0:
        return keep
    pooled = torch.nn.functional.max_pool1d(keep[:, None].float(), 2 * radius + 1, stride=1, padding=radius)
    return pooled[:, 0] > 0


def split_bins(lo: Tensor, hi: Tensor, ray: Tensor, counts: Tensor, generator: torch.Generator | None) -> PackedSamples:
    """Bin k of [lo_k, hi_k) split into counts_k stratified sub-intervals (inner edges jittered with a
    generator); bins must come grouped by ray in increasing t, and so do the samples."""
    bin_of = torch.repeat_interleave(torch.arange(len(lo), device=lo.device), counts)
    first = torch.cumsum(counts, 0) - counts
    j = torch.arange(len(bin_of), device=lo.device) - first[bin_of]  # sub-interval index inside its bin
    c, width = counts[bin_of].to(lo.dtype), (hi - lo)[bin_of]
    shift = torch.zeros_like(c)
    if generator is not None:
        shift = torch.rand(len(c), generator=generator, device=lo.device, dtype=lo.dtype) - 0.5
        shift = torch.where(j > 0, shift, torch.zeros_like(shift))  # the bin's own start edge stays put
    starts = lo[bin_of] + width * (j + shift) / c
    last = j == counts[bin_of] - 1
    ends = torch.where(last, hi[bin_of], torch.roll(starts, -1))
    return PackedSamples(starts, ends, ray[bin_of])


def guided_samples(
    near: Tensor, far: Tensor, origins: Tensor, directions: Tensor, occupied: Callable[[Tensor], Tensor],
    num_coarse: int, split: int, generator: torch.Generator | None, jitter: bool = False, dilate: int = 0,
    fallback: bool = False, only_hits: bool = False,
) -> tuple[PackedSamples, Tensor]:
    """LeCO guided sampling; returns the packed fine samples and the kept fraction of coarse samples
    (the occupancy ratio). The paper's sampler is the default: O at fixed bin mid-points, kept bins split in
    `split`, rays with nothing kept render the background only. Options (issue 16): `jitter` queries O at a
    random point of each bin while training (a generator is given), so a surface between mid-points is found
    on some steps; `dilate` keeps the neighbours of kept bins along the ray; `fallback` gives a ray with no
    kept bin one sample per coarse bin. `only_hits` asks O about the rays that cross the box only (the rest
    have no bin to keep): the same samples, fewer queries when many rays miss it, as a rendered view's sky does;
    the online learner needs O's logits for every bin, so training leaves it off."""
    edges = stratified_edges(near, far, num_coarse, None)  # coarse bins are fixed; jitter happens inside them
    lo_all, hi_all = edges[:, :-1], edges[:, 1:]
    u: Tensor | float = 0.5
    if jitter and generator is not None:
        u = torch.rand(lo_all.shape, generator=generator, device=near.device, dtype=near.dtype)
    t = lo_all + (hi_all - lo_all) * u
    points = origins[:, None, :] + directions[:, None, :] * t[..., None]
    valid = (far > near)[:, None]
    if only_hits:
        hits = valid[:, 0]
        occupied_bins = torch.zeros(t.shape, dtype=torch.bool, device=near.device)
        if bool(hits.any()):
            occupied_bins[hits] = occupied(points[hits].reshape(-1, 3)).reshape(-1, t.shape[1])
    else:
        occupied_bins = occupied(points.reshape(-1, 3)).reshape(t.shape) & valid
    keep = dilate_bins(occupied_bins, dilate) & valid
    counts = torch.full_like(keep, split, dtype=torch.long)
    if fallback:
        lost = ~keep.any(dim=1) & valid[:, 0]
        keep = keep | lost[:, None]
        counts[lost] = 1
    ray, bin_ = torch.nonzero(keep, as_tuple=True)  # row-major: grouped by ray, increasing t
    samples = split_bins(edges[ray, bin_], edges[ray, bin_ + 1], ray, counts[ray, bin_],
                         generator if split > 1 else None)
    return samples, occupied_bins.float().mean()

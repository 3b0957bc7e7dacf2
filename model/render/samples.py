"""Samples along rays as intervals [start, end) inside each ray's foreground segment [near, far].

- stratified: n equal bins with one jittered interval each (coarse);
- inverse-CDF: n more intervals drawn from coarse weights (fine); merged with the coarse ones;
- guided (LeCO, section 3.4): coarse bins -> occupancy predictor -> drop unoccupied -> split each
  kept bin into k stratified sub-intervals, returned packed (flat samples + ray index).
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
        """The samples where keep is true, in the same order (so still grouped by ray, increasing
        t)."""
        return PackedSamples(self.starts[keep], self.ends[keep], self.ray_index[keep])


def stratified_edges(
    near: Tensor, far: Tensor, n: int, generator: torch.Generator | None
) -> Tensor:
    """(R, n + 1) bin edges; with a generator the inner edges are jittered inside their bins
    (training)."""
    u = torch.linspace(0.0, 1.0, n + 1, device=near.device)
    if generator is not None:
        jitter = (torch.rand(len(near), n - 1, generator=generator, device=near.device) - 0.5) / n
        u = u.expand(len(near), n + 1).clone()
        u[:, 1:-1] += jitter
    return near[:, None] + (far - near)[:, None] * u


def inverse_cdf_edges(
    edges: Tensor, weights: Tensor, n: int, generator: torch.Generator | None
) -> Tensor:
    """(R, n) new sample positions distributed like the coarse weights (piecewise-constant pdf)."""
    pdf = weights.detach() + 1e-5  # keep every bin reachable and empty rays uniform
    cdf = torch.cat(
        [torch.zeros_like(pdf[:, :1]), (pdf / pdf.sum(-1, keepdim=True)).cumsum(-1)], -1
    )
    if generator is None:
        u = (
            torch.linspace(0.0, 1.0, n + 2, device=edges.device)[1:-1]
            .expand(len(edges), n)
            .contiguous()
        )
    else:
        u = torch.rand(len(edges), n, generator=generator, device=edges.device)
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


def dilate_bins(keep: Tensor, radius: int) -> Tensor:
    """Also keep every bin within `radius` bins of a kept one along its ray (a 1-D max filter)."""
    if radius == 0 or keep.shape[1] == 0:
        return keep
    pooled = torch.nn.functional.max_pool1d(
        keep[:, None].float(), 2 * radius + 1, stride=1, padding=radius
    )
    return pooled[:, 0] > 0


def split_bins(
    lo: Tensor, hi: Tensor, ray: Tensor, counts: Tensor, generator: torch.Generator | None
) -> PackedSamples:
    """Bin k of [lo_k, hi_k) split into counts_k stratified sub-intervals (inner edges jittered with
    a generator); bins must come grouped by ray in increasing t, and so do the samples."""
    bin_of = torch.repeat_interleave(torch.arange(len(lo), device=lo.device), counts)
    first = torch.cumsum(counts, 0) - counts
    # sub-interval index inside its bin
    j = torch.arange(len(bin_of), device=lo.device) - first[bin_of]
    c, width = counts[bin_of].to(lo.dtype), (hi - lo)[bin_of]
    shift = torch.zeros_like(c)
    if generator is not None:
        shift = torch.rand(len(c), generator=generator, device=lo.device, dtype=lo.dtype) - 0.5
        # the bin's own start edge stays put
        shift = torch.where(j > 0, shift, torch.zeros_like(shift))
    starts = lo[bin_of] + width * (j + shift) / c
    last = j == counts[bin_of] - 1
    ends = torch.where(last, hi[bin_of], torch.roll(starts, -1))
    return PackedSamples(starts, ends, ray[bin_of])


def select_bins(
    occupied_bins: Tensor,
    dilate: int = 0,
    fallback: bool = False,
    scores: Tensor | None = None,
    topk: int = 0,
) -> tuple[Tensor, Tensor]:
    """The bins (R, n) the main network samples, from O's decisions on hit rays: dilated by `dilate`
    bins, and with `fallback` a ray that keeps nothing gets its `topk` best-scored bins (`scores`:
    O's decision logits) or, with topk 0, every bin. Returns (keep, lost): lost marks the rays that
    took the fallback."""
    keep = dilate_bins(occupied_bins, dilate)
    lost = ~keep.any(dim=1)
    if not fallback:
        return keep, torch.zeros_like(lost)
    if topk > 0 and scores is not None:
        best = scores.topk(min(topk, scores.shape[1]), dim=1).indices
        chosen = torch.zeros_like(keep).scatter_(1, best, True)
        return keep | (chosen & lost[:, None]), lost
    return keep | lost[:, None], lost


@dataclass
class GuidedDraw:
    samples: PackedSamples  # the main network's samples
    occupied_bins: Tensor  # (R, n) O's own decisions (False on rays that miss the box)
    lost: Tensor  # (R,) hit rays that kept nothing and took the fallback
    edges: Tensor  # (R, n + 1) the coarse bins


def draw_guided(
    near: Tensor,
    far: Tensor,
    origins: Tensor,
    directions: Tensor,
    occupied: Callable[[Tensor], Tensor],
    num_coarse: int,
    split: int,
    generator: torch.Generator | None,
    jitter: bool = False,
    dilate: int = 0,
    fallback: bool = False,
    topk: int = 0,
    scores: Callable[[], Tensor] | None = None,
    place: Callable[[Tensor, Tensor, Tensor], PackedSamples] | None = None,
    queries: int = 1,
) -> GuidedDraw:
    """LeCO's guided sampling (section 3.4). The paper's sampler is the default: O at fixed bin
    mid-points, kept bins split in `split`, rays with nothing kept render the background only.
    Options:
    - `jitter`: O is asked at a random point of each bin while training (a generator is given), so a
      surface between mid-points is found on some steps;
    - `dilate`: the neighbours of kept bins along the ray are kept too;
    - `fallback`: a ray with nothing kept samples every coarse bin once, or with `topk` its k bins
      that O scores highest (`scores()`: the decision logits of the last `occupied` call), split
      like kept bins;
    - `place(rows, edges, keep)`: draws the samples of these rows over their kept bins instead of
      splitting them (model/estimators/placement.py);
    - `queries`: O is asked at that many points of each bin (stratified inside it) and the bin is
      kept when any of them is, so a surface that fills only part of a bin (the ground in a flat
      box's last bin) is found.
    O is asked about the rays that cross the box only: the others have no bin to keep."""
    # coarse bins are fixed; jitter happens inside them
    edges = stratified_edges(near, far, num_coarse, None)
    lo_all, hi_all = edges[:, :-1, None], edges[:, 1:, None]
    u = (torch.arange(queries, device=near.device, dtype=near.dtype) + 0.5) / queries
    if jitter and generator is not None:
        u = (
            u
            + (
                torch.rand(
                    (*edges[:, 1:].shape, queries),
                    generator=generator,
                    device=near.device,
                    dtype=near.dtype,
                )
                - 0.5
            )
            / queries
        )
    t = lo_all + (hi_all - lo_all) * u  # (R, n, queries)
    points = origins[:, None, None, :] + directions[:, None, None, :] * t[..., None]
    hits = far > near
    occupied_bins = torch.zeros(t.shape[:2], dtype=torch.bool, device=near.device)
    score: Tensor | None = None
    if bool(hits.any()):
        asked = occupied(points[hits].reshape(-1, 3)).reshape(-1, num_coarse, queries)
        occupied_bins[hits] = asked.any(dim=-1)
        if topk > 0 and scores is not None:
            score = torch.full(t.shape[:2], -torch.inf, device=near.device)
            score[hits] = scores().reshape(-1, num_coarse, queries).amax(dim=-1).to(score.dtype)
    keep, lost = select_bins(occupied_bins, dilate, fallback, score, topk)
    keep, lost = keep & hits[:, None], lost & hits
    if place is not None:
        rows = torch.nonzero(keep.any(dim=1))[:, 0]
        drawn = place(rows, edges[rows], keep[rows])
        samples = PackedSamples(drawn.starts, drawn.ends, rows[drawn.ray_index])
        return GuidedDraw(samples, occupied_bins, lost, edges)
    counts = torch.full_like(keep, split, dtype=torch.long)
    if topk == 0:
        counts[lost] = 1
    ray, bin_ = torch.nonzero(keep, as_tuple=True)  # row-major: grouped by ray, increasing t
    samples = split_bins(
        edges[ray, bin_],
        edges[ray, bin_ + 1],
        ray,
        counts[ray, bin_],
        generator if split > 1 else None,
    )
    return GuidedDraw(samples, occupied_bins, lost, edges)


def guided_samples(
    near: Tensor,
    far: Tensor,
    origins: Tensor,
    directions: Tensor,
    occupied: Callable[[Tensor], Tensor],
    num_coarse: int,
    split: int,
    generator: torch.Generator | None,
    **options,
) -> tuple[PackedSamples, Tensor]:
    """`draw_guided`'s samples and the fraction of the hit rays' coarse bins that O itself keeps
    (before dilation and fallback; model/render/accounting.py counts what reaches the main
    network)."""
    draw = draw_guided(
        near, far, origins, directions, occupied, num_coarse, split, generator, **options
    )
    hits = far > near
    kept = draw.occupied_bins[hits].float().mean() if bool(hits.any()) else near.new_zeros(())
    return draw.samples, kept

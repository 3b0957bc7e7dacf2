"""LeCO's guided sampler (paper section 3.4): coarse bins -> O keeps or drops each -> the kept ones
split into stratified sub-intervals (or placed by O's head, model/estimators/placement.py), returned
packed. The paper's sampler is BinOptions' defaults; each option is a `guided.*` setting."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import torch
from torch import Tensor

from model.profiles import GuidedConfig
from model.render.noise import Noise
from model.render.samples import PackedSamples, split_bins, stratified_edges


@dataclass(frozen=True)
class BinOptions:
    """How O's answers become the bins the main network samples."""

    coarse: int  # coarse bins per ray, each asked of O (guided.coarse_samples)
    split: int  # stratified samples per kept bin (guided.split)
    # O is asked at a random point of each bin while training (noise is given), so a surface
    # between mid-points is found on some steps (guided.jitter)
    jitter: bool = False
    dilate: int = 0  # the neighbours of kept bins along the ray are kept too (guided.dilate)
    # a ray with nothing kept samples every coarse bin once, or with `topk` its k bins that O scores
    # highest, split like kept bins (guided.fallback, guided.fallback_topk)
    fallback: bool = False
    topk: int = 0
    # O is asked at this many points of each bin and the bin is kept when any of them is, so a
    # surface that fills only part of a bin is found (guided.queries_per_bin)
    queries: int = 1
    # while training, each ray also samples this many bins O dropped, at random, so the main network
    # renders (and O's online loss labels) a surface O missed (guided.explore_bins)
    explore: int = 0

    @classmethod
    def of(cls, g: GuidedConfig) -> "BinOptions":
        return cls(
            g.coarse_samples,
            g.split,
            g.jitter,
            g.dilate,
            g.fallback,
            g.fallback_topk,
            g.queries_per_bin,
            g.explore_bins,
        )


def dilate_bins(keep: Tensor, radius: int) -> Tensor:
    """Also keep every bin within `radius` bins of a kept one along its ray (a 1-D max filter)."""
    if radius == 0 or keep.shape[1] == 0:
        return keep
    pooled = torch.nn.functional.max_pool1d(
        keep[:, None].float(), 2 * radius + 1, stride=1, padding=radius
    )
    return pooled[:, 0] > 0


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


def explored_bins(keep: Tensor, count: int, noise: Noise) -> Tensor:
    """`count` bins per ray that `keep` (R, n) drops, drawn uniformly among them (fewer where
    fewer are dropped): the largest of a uniform draw per dropped bin, without a host read."""
    draw = noise.rand(*keep.shape, device=keep.device).masked_fill(keep, -1.0)
    picked = draw.topk(min(count, keep.shape[1]), dim=1).indices
    return torch.zeros_like(keep).scatter_(1, picked, True) & ~keep


@dataclass
class GuidedDraw:
    samples: PackedSamples  # the main network's samples
    occupied_bins: Tensor  # (R, n) O's own decisions (False on rays that miss the box)
    lost: Tensor  # (R,) hit rays that kept nothing and took the fallback
    edges: Tensor  # (R, n + 1) the coarse bins


@dataclass
class KeptBins:
    """O's answer for a batch of rays, before any sample is drawn."""

    edges: Tensor  # (R, n + 1) the coarse bins
    keep: Tensor  # (R, n) the bins to sample: O's decisions dilated, with the fallback
    occupied_bins: Tensor  # (R, n) O's own decisions (False on rays that miss the box)
    lost: Tensor  # (R,) hit rays that kept nothing and took the fallback


def keep_bins(
    near: Tensor,
    far: Tensor,
    origins: Tensor,
    directions: Tensor,
    occupied: Callable[[Tensor], Tensor],
    noise: Noise | None,
    options: BinOptions,
    scores: Callable[[], Tensor] | None = None,
    all_hit: bool = False,
) -> KeptBins:
    """O keeps or drops each of `options.coarse` bins of a ray (section 3.4), then dilation and the
    fallback (BinOptions). `scores()`: the decision logits of the last `occupied` call (for the
    top-k fallback). O is asked about the rays that cross the box only: the others have no bin to
    keep. `all_hit`: the caller passes only rays that cross the box, so O is asked about every ray
    without a mask to gather by (the same answer, no wait on the mask's size)."""
    num_coarse, queries = options.coarse, options.queries
    # coarse bins are fixed; jitter happens inside them
    edges = stratified_edges(near, far, num_coarse, None)
    lo_all, hi_all = edges[:, :-1, None], edges[:, 1:, None]
    u = (torch.arange(queries, device=near.device, dtype=near.dtype) + 0.5) / queries
    if options.jitter and noise is not None:
        u = (
            u
            + (
                noise.rand(
                    *edges[:, 1:].shape,
                    queries,
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
    if all_hit:
        if len(near):
            asked = occupied(points.reshape(-1, 3)).reshape(-1, num_coarse, queries)
            occupied_bins = asked.any(dim=-1)
            if options.topk > 0 and scores is not None:
                score = scores().reshape(-1, num_coarse, queries).amax(dim=-1).float()
        elif options.topk > 0 and scores is not None:
            score = torch.full(t.shape[:2], -torch.inf, device=near.device)
    elif bool(hits.any()):
        asked = occupied(points[hits].reshape(-1, 3)).reshape(-1, num_coarse, queries)
        occupied_bins[hits] = asked.any(dim=-1)
        if options.topk > 0 and scores is not None:
            score = torch.full(t.shape[:2], -torch.inf, device=near.device)
            score[hits] = scores().reshape(-1, num_coarse, queries).amax(dim=-1).to(score.dtype)
    keep, lost = select_bins(occupied_bins, options.dilate, options.fallback, score, options.topk)
    return KeptBins(edges, keep & hits[:, None], occupied_bins, lost & hits)


def draw_guided(
    near: Tensor,
    far: Tensor,
    origins: Tensor,
    directions: Tensor,
    occupied: Callable[[Tensor], Tensor],
    noise: Noise | None,
    options: BinOptions,
    scores: Callable[[], Tensor] | None = None,
    place: Callable[[Tensor, Tensor, Tensor], PackedSamples] | None = None,
    all_hit: bool = False,
) -> GuidedDraw:
    """LeCO's guided sampling (section 3.4): O keeps or drops each of `options.coarse` bins of a
    ray (`keep_bins`), the kept ones are split (BinOptions says how). `place(rows, edges, keep)`:
    draws the samples of these rows over their kept bins instead of splitting them
    (model/estimators/placement.py). `all_hit`: as in `keep_bins`."""
    bins = keep_bins(near, far, origins, directions, occupied, noise, options, scores, all_hit)
    edges, keep, lost, split = bins.edges, bins.keep, bins.lost, options.split
    if place is not None:
        rows = torch.nonzero(keep.any(dim=1))[:, 0]
        drawn = place(rows, edges[rows], keep[rows])
        samples = PackedSamples(drawn.starts, drawn.ends, rows[drawn.ray_index])
        return GuidedDraw(samples, bins.occupied_bins, lost, edges)
    counts = torch.full_like(keep, split, dtype=torch.long)
    if options.topk == 0:
        counts[lost] = 1
    if options.explore and noise is not None and keep.shape[1]:
        keep = keep | (explored_bins(keep, options.explore, noise) & (far > near)[:, None])
    ray, bin_ = torch.nonzero(keep, as_tuple=True)  # row-major: grouped by ray, increasing t
    samples = split_bins(
        edges[ray, bin_],
        edges[ray, bin_ + 1],
        ray,
        counts[ray, bin_],
        noise if split > 1 else None,
    )
    return GuidedDraw(samples, bins.occupied_bins, lost, edges)


def guided_samples(
    near: Tensor,
    far: Tensor,
    origins: Tensor,
    directions: Tensor,
    occupied: Callable[[Tensor], Tensor],
    num_coarse: int,
    split: int,
    noise: Noise | None,
    scores: Callable[[], Tensor] | None = None,
    place: Callable[[Tensor, Tensor, Tensor], PackedSamples] | None = None,
    **options: Any,
) -> tuple[PackedSamples, Tensor]:
    """`draw_guided`'s samples (BinOptions from `num_coarse`, `split` and the other options by
    name) and the fraction of the hit rays' coarse bins that O itself keeps (before dilation and
    fallback; model/render/accounting.py counts what reaches the main network)."""
    bins = BinOptions(num_coarse, split, **options)
    draw = draw_guided(near, far, origins, directions, occupied, noise, bins, scores, place)
    hits = far > near
    kept = draw.occupied_bins[hits].float().mean() if bool(hits.any()) else near.new_zeros(())
    return draw.samples, kept

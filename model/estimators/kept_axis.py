"""The axis a bounded sampler draws on: where O says a ray may hold a surface, laid end to end.

LeCO's O decides, per coarse bin of a ray, whether the bin may hold a surface (section 3.4). A
proposal sampler bounded by O (`leco-prop`) draws its levels on a coordinate s that runs only over
the bins O lets it use, in one of three forms (`leco_prop.bound`):

- range: every bin from the first kept one to the last (the ray's near and far move in);
- mask: the kept bins only, laid end to end, so no interval straddles a dropped bin;
- off: the whole segment, as S+Prop (the control arm: phase 1 and the warm start without the bound).

An interval [s0, s1] on the axis becomes a sample at t(mid) with delta s1 - s0: a dropped bin is
zero long in s and holds no density, as O says (the convention of model/estimators/placement.py)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch
from torch import Tensor

BOUNDS = ("range", "mask", "off")


class Axis(Protocol):
    """Where a ray's samples are drawn: [start, end] per ray, and each coordinate's depth t."""

    @property
    def start(self) -> Tensor: ...  # (R,)

    @property
    def end(self) -> Tensor: ...  # (R,)

    def to_t(self, x: Tensor) -> Tensor: ...


@dataclass
class SegmentAxis:
    """The ray's own segment [near, far]: s is t (S+Prop)."""

    start: Tensor
    end: Tensor

    def to_t(self, x: Tensor) -> Tensor:
        return x


def bounded(keep: Tensor, bound: str) -> Tensor:
    """The bins (R, B) a bounded sampler may use, from the bins O's sampler keeps: `range` fills
    each ray from its first kept bin to its last, `mask` is `keep` itself, `off` is every bin. A
    ray with nothing kept keeps nothing (it missed the box, or the fallback is off)."""
    if bound == "mask":
        return keep
    if bound == "off":
        return torch.ones_like(keep)
    if bound != "range":
        raise ValueError(f"unknown bound {bound!r}: choose one of {', '.join(BOUNDS)}")
    seen = keep.cumsum(dim=1) > 0  # at or after the first kept bin
    left = keep.flip(1).cumsum(dim=1).flip(1) > 0  # at or before the last
    return seen & left


@dataclass
class KeptAxis:
    """s over the kept bins of each ray laid end to end: [0, kept length]. With `explore` > 0 a
    dropped bin is not skipped but shrunk to that share of its length, so about that share of a
    uniform draw looks where O says nothing is (`leco_prop.explore`): a surface O dropped can catch
    weight there and O, learning online from the main weights, learns to keep it. A sample there
    has its delta shrunk alike, so the field needs a higher density to stop the ray in it."""

    edges: Tensor  # (R, B + 1) the coarse bins in t
    keep: Tensor  # (R, B) the bins the axis runs over at full length
    scale: Tensor  # (R, B) each bin's length on the axis per unit of t (1 kept, `explore` dropped)
    s_edges: Tensor  # (R, B + 1) each bin's edges in s (a dropped bin is zero long without explore)

    @classmethod
    def of(cls, edges: Tensor, keep: Tensor, explore: float = 0.0) -> "KeptAxis":
        # a ray that keeps nothing (it missed the box) gets no length at all
        anything = keep.any(dim=1, keepdim=True)
        scale = torch.where(keep, 1.0, explore * anything).to(edges.dtype)
        width = (edges[:, 1:] - edges[:, :-1]) * scale
        s_edges = torch.cat([torch.zeros_like(width[:, :1]), width.cumsum(-1)], -1)
        return cls(edges, keep, scale, s_edges)

    @property
    def start(self) -> Tensor:
        return self.s_edges[:, 0]

    @property
    def end(self) -> Tensor:
        return self.s_edges[:, -1]

    def to_t(self, s: Tensor) -> Tensor:
        """Depths (R, M) of axis coordinates (R, M). A coordinate where a zero-long dropped bin
        separates two kept ones goes to the start of the later one (`right=True` picks the last bin
        starting at or before s: the dropped bins before it start there too); the end of the axis
        goes to the end of the last bin it runs over, not to zero-long bins after it."""
        b = self.keep.shape[1]
        s_edges = self.s_edges.contiguous()
        bin_ = (torch.searchsorted(s_edges, s.contiguous(), right=True) - 1).clamp(0, b - 1)
        # only past the last bin with length can that land on a zero-long one: take the bin that
        # ends there
        ending = torch.searchsorted(s_edges[:, 1:].contiguous(), s.contiguous()).clamp(0, b - 1)
        scale = self.scale.gather(1, bin_)
        bin_ = torch.where(scale > 0, bin_, ending)
        scale = self.scale.gather(1, bin_).clamp(min=1e-30)
        return self.edges.gather(1, bin_) + (s - self.s_edges.gather(1, bin_)) / scale

    def length(self) -> Tensor:
        """(R,) each ray's length on the axis."""
        return self.end - self.start

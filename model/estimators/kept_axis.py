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
    """s over the kept bins of each ray laid end to end: [0, kept length]."""

    edges: Tensor  # (R, B + 1) the coarse bins in t
    keep: Tensor  # (R, B) the bins the axis runs over
    s_edges: Tensor  # (R, B + 1) each bin's edges in s (a dropped bin is zero long)

    @classmethod
    def of(cls, edges: Tensor, keep: Tensor) -> "KeptAxis":
        width = (edges[:, 1:] - edges[:, :-1]) * keep
        return cls(edges, keep, torch.cat([torch.zeros_like(width[:, :1]), width.cumsum(-1)], -1))

    @property
    def start(self) -> Tensor:
        return self.s_edges[:, 0]

    @property
    def end(self) -> Tensor:
        return self.s_edges[:, -1]

    def to_t(self, s: Tensor) -> Tensor:
        """Depths (R, M) of axis coordinates (R, M). A coordinate where a dropped bin separates two
        kept ones goes to the start of the later one (`right=True` picks the last bin starting at or
        before s: the dropped bins before it are zero long and start there too); the end of the
        axis goes to the end of the last kept bin, not to dropped bins after it."""
        b = self.keep.shape[1]
        s_edges = self.s_edges.contiguous()
        bin_ = (torch.searchsorted(s_edges, s.contiguous(), right=True) - 1).clamp(0, b - 1)
        # only past the last kept bin can that land on a dropped one: take the bin that ends there
        ending = torch.searchsorted(s_edges[:, 1:].contiguous(), s.contiguous()).clamp(0, b - 1)
        bin_ = torch.where(self.keep.gather(1, bin_), bin_, ending)
        return self.edges.gather(1, bin_) + (s - self.s_edges.gather(1, bin_))

    def length(self) -> Tensor:
        """(R,) each ray's kept length in t units."""
        return self.end - self.start

"""Exact ray casting against the city: the ground plane z = 0 and axis-aligned boxes (slab test).

Everything is float64, so a depth is exact to machine precision and a ray grazing an edge is decided
the same way every time. Speed comes from culling, which never changes a result: rays are sorted so
that each chunk covers a small part of the district, and a chunk is only tested against the boxes
that overlap the bounding box of its rays' segments inside the scene (a hit point lies on the
segment and on the box)."""

from __future__ import annotations

import torch
from torch import Tensor

from model.scenes.synthetic.geometry import CityGeometry

SKY, GROUND = -1, 0
# rays per chunk: small chunks cull more boxes; the Python loop cost stays ~1 ms a chunk
CHUNK = 2048
SORT_CELL = 8.0  # metres: the xy cell of the sort key (a few streets wide)
TINY = 1e-30  # stands in for a zero direction component (keeps its sign, avoids 0 * inf = nan)
SLACK = 1e-6  # metres added around each chunk's bounding box against rounding in the culling test


def raycast(
    geometry: CityGeometry, origins: Tensor, dirs: Tensor, t_max: float = float("inf")
) -> tuple[Tensor, Tensor, Tensor]:
    """First hit of each ray at 0 < t <= t_max: t (inf for none), hit id (-1 sky, 0 ground, 1 + k
    box k), outward unit normal (zero for sky). Rays that start inside a box ignore that box."""
    o, d = origins.double(), dirs.double()
    n = len(o)
    t = torch.full((n,), float("inf"), dtype=torch.float64)
    hit = torch.full((n,), SKY, dtype=torch.long)
    normal = torch.zeros(n, 3, dtype=torch.float64)

    down = d[:, 2] < 0
    t_ground = torch.where(down, -o[:, 2] / torch.where(down, d[:, 2], -1.0), torch.inf)
    ground = down & (t_ground >= 0) & (t_ground <= t_max)  # t_ground is inf for the rest
    t[ground] = t_ground[ground]
    hit[ground] = GROUND
    normal[ground, 2] = 1.0
    if len(geometry.boxes) == 0 or n == 0:
        return t, hit, normal

    lo, hi = geometry.boxes[:, 0].double(), geometry.boxes[:, 1].double()
    inv = 1.0 / safe(d)
    # The part of each ray inside the bounding box of all boxes, before the ground and t_max.
    t_in, t_out = slab(lo.amin(0), hi.amax(0), o, inv)
    t_in, t_out = t_in.clamp(min=0.0), torch.minimum(t_out, t.clamp(max=t_max))
    live = torch.nonzero(t_in <= t_out).squeeze(1)
    if len(live) == 0:
        return t, hit, normal
    a = o[live] + d[live] * t_in[live, None]  # segment ends
    b = o[live] + d[live] * t_out[live, None]
    order = live[torch.argsort(morton(0.5 * (a[:, :2] + b[:, :2])), stable=True)]
    seg_lo = torch.empty(n, 3, dtype=torch.float64)
    seg_hi = torch.empty(n, 3, dtype=torch.float64)
    seg_lo[live], seg_hi[live] = torch.minimum(a, b), torch.maximum(a, b)

    for rays in order.split(CHUNK):
        chunk_lo, chunk_hi = seg_lo[rays].amin(0) - SLACK, seg_hi[rays].amax(0) + SLACK
        near = torch.nonzero(((lo <= chunk_hi) & (hi >= chunk_lo)).all(-1)).squeeze(1)
        if len(near) == 0:
            continue
        box_t, k, axis = nearest_box(lo[near], hi[near], o[rays], inv[rays])
        better = box_t < t[rays]
        if t_max < float("inf"):
            better &= box_t <= t_max
        rays, box_t, k, axis = rays[better], box_t[better], k[better], axis[better]
        t[rays] = box_t
        hit[rays] = near[k] + 1
        normal[rays] = 0.0
        normal[rays, axis] = -torch.sign(d[rays, axis])
    return t, hit, normal


def safe(d: Tensor) -> Tensor:
    """Direction with exact zeros replaced by +-TINY (sign kept), so 1/d is finite."""
    sign = torch.where(torch.signbit(d), -1.0, 1.0).to(d.dtype)
    return torch.where(d.abs() < TINY, sign * TINY, d)


def slab(lo: Tensor, hi: Tensor, o: Tensor, inv: Tensor) -> tuple[Tensor, Tensor]:
    """Entry and exit distance of each ray through one box (entry > exit: a miss)."""
    t0, t1 = (lo - o) * inv, (hi - o) * inv
    return torch.minimum(t0, t1).amax(-1), torch.maximum(t0, t1).amin(-1)


def nearest_box(lo: Tensor, hi: Tensor, o: Tensor, inv: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Entry distance, index and entry axis of the nearest box each ray enters from outside (inf if
    none)."""
    t0 = (lo[None] - o[:, None]) * inv[:, None]  # (R, K, 3)
    t1 = (hi[None] - o[:, None]) * inv[:, None]
    t_near, axis = torch.minimum(t0, t1).max(dim=-1)
    t_far = torch.maximum(t0, t1).amin(dim=-1)
    t_near = torch.where((t_far >= t_near) & (t_near > 0), t_near, torch.inf)
    best, k = t_near.min(dim=1)
    return best, k, axis.gather(1, k[:, None]).squeeze(1)


def morton(xy: Tensor) -> Tensor:
    """Z-order key of xy on a SORT_CELL grid: rays close in the key are close in space."""
    cell = torch.floor((xy - xy.amin(0)) / SORT_CELL).long().clamp(0, 0xFFFF)
    key = torch.zeros(len(xy), dtype=torch.long)
    for bit in range(16):
        key |= ((cell[:, 0] >> bit) & 1) << (2 * bit) | ((cell[:, 1] >> bit) & 1) << (2 * bit + 1)
    return key

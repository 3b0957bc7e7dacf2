"""Exact ray casting against the city: the ground plane z = 0 and axis-aligned boxes (slab test)."""

from __future__ import annotations

import torch
from torch import Tensor

from model.scenes.synthetic.city import CityGeometry

SKY, GROUND = -1, 0
CHUNK = 8192


def raycast(
    geometry: CityGeometry, origins: Tensor, dirs: Tensor, t_max: float = float("inf")
) -> tuple[Tensor, Tensor, Tensor]:
    """First hit of each ray: t (inf for sky), hit id (-1 sky, 0 ground, 1 + k box k), outward normal."""
    origins, dirs = origins.double(), dirs.double()
    t = torch.full((len(origins),), float("inf"), dtype=torch.float64)
    hit = torch.full((len(origins),), SKY, dtype=torch.long)
    normal = torch.zeros(len(origins), 3, dtype=torch.float64)

    going_down = dirs[:, 2] < 0
    t_ground = torch.where(going_down, -origins[:, 2] / torch.where(going_down, dirs[:, 2], -1.0), torch.inf)
    ground = (t_ground >= 0) & (t_ground < t_max)
    t = torch.where(ground, t_ground, t)
    hit[ground] = GROUND
    normal[ground] = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)

    boxes = geometry.boxes.float()
    for s in range(0, len(origins), CHUNK):
        o, d = origins[s : s + CHUNK], dirs[s : s + CHUNK]
        box_t, box_id, box_axis = nearest_box(boxes, o.float(), d.float())
        better = box_t.double() < torch.minimum(t[s : s + CHUNK], torch.full_like(box_t.double(), t_max))
        idx = torch.nonzero(better).squeeze(1)
        if len(idx) == 0:
            continue
        # Recompute the entry distance in float64 for the chosen box: float32 only picks the box.
        k, axis = box_id[idx], box_axis[idx]
        oo, dd = o[idx], d[idx]
        rows = torch.arange(len(idx))
        safe = torch.where(dd.abs() < 1e-300, torch.full_like(dd, 1e-300), dd)
        plane = torch.where(dd[rows, axis] > 0, geometry.boxes[k, 0, axis], geometry.boxes[k, 1, axis])
        t[s + idx] = (plane - oo[rows, axis]) / safe[rows, axis]
        hit[s + idx] = k + 1
        n = torch.zeros(len(idx), 3, dtype=torch.float64)
        n[rows, axis] = -torch.sign(dd[rows, axis])
        normal[s + idx] = n
    return t, hit, normal


def nearest_box(boxes: Tensor, o: Tensor, d: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Entry distance, index and entry axis of the nearest box each ray hits from outside (inf if none)."""
    inv = 1.0 / torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
    t0 = (boxes[None, :, 0, :] - o[:, None, :]) * inv[:, None, :]
    t1 = (boxes[None, :, 1, :] - o[:, None, :]) * inv[:, None, :]
    t_near_axes = torch.minimum(t0, t1)
    t_near, axis = t_near_axes.max(dim=-1)
    t_far = torch.maximum(t0, t1).amin(dim=-1)
    valid = (t_far >= t_near) & (t_near > 0)
    t_near = torch.where(valid, t_near, torch.full_like(t_near, float("inf")))
    best, k = t_near.min(dim=1)
    return best, k, axis.gather(1, k[:, None]).squeeze(1)

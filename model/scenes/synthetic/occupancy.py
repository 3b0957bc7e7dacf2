"""Exact ground-truth occupancy of the district: a cell is occupied iff its volume overlaps a solid
(a box, or the ground half-space z <= 0) with positive volume. Computed per box from index
ranges."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from model.scenes.synthetic.geometry import CityGeometry

MARGIN = 5.0  # metres of ground around the district inside the grid


def occupancy_grid(geometry: CityGeometry) -> tuple[Tensor, Tensor, float]:
    """(occupied bool (X, Y, Z) with i east, j north, k up; grid minimum corner in metres; cell
    size)."""
    cell = geometry.preset.cell_size
    half = geometry.extent / 2 + MARGIN
    xy_cells = math.ceil(2 * half / cell)
    # one layer below the ground, air above the top
    z_cells = 1 + math.ceil((geometry.top + cell) / cell)
    grid_min = torch.tensor([-half, -half, -cell], dtype=torch.float64)
    occupied = torch.zeros(xy_cells, xy_cells, z_cells, dtype=torch.bool)
    occupied[:, :, 0] = True  # the layer below z = 0 is ground
    shape = torch.tensor(occupied.shape)
    for lo, hi in geometry.boxes:
        # Cell i spans [i, i+1] in cell units: it overlaps (lo', hi') with positive length iff lo' -
        # 1 < i < hi'.
        i0 = torch.floor(snap((lo - grid_min) / cell)).long().clamp(min=0)
        i1 = torch.ceil(snap((hi - grid_min) / cell)).long()
        i1 = torch.minimum(i1, shape)
        occupied[i0[0] : i1[0], i0[1] : i1[1], i0[2] : i1[2]] = True
    return occupied, grid_min, cell


def snap(x: Tensor) -> Tensor:
    """A face meant to lie on a cell boundary (a 4.0 m roof on 0.5 m cells) must not claim a
    zero-volume sliver of the next cell through rounding: values within 1e-9 of an integer become
    that integer."""
    nearest = torch.round(x)
    return torch.where((x - nearest).abs() < 1e-9, nearest, x)

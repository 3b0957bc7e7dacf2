"""Seeded procedural countryside: open fields, woods, hedgerows and a few farmsteads on a wide
square of parcels, sparser and lower than the city. Everything is an axis-aligned box on the
ground plane, so depth and occupancy stay exact: a tree is a trunk under two stacked canopy boxes.

Frame: metres, x east, y north, z up; the parcels are centred on the origin and separated by
grass lanes `street_width` wide (one of them a dirt road).
"""

from __future__ import annotations

import numpy as np
import torch

from model.scenes.synthetic.geometry import (
    BUILDING,
    CANOPY,
    HEDGE,
    MAST,
    TRUNK,
    Boxes,
    CityGeometry,
    district_extent,
)
from model.scenes.synthetic.presets import CityPreset

# What covers a parcel's ground (CityGeometry.parcels): shading.village_ground_albedo colours it.
MEADOW, WHEAT, YOUNG_CROP, PLOUGHED = 0, 1, 2, 3
# Shares of the parcels: farmsteads and woods; the rest are fields (or meadow).
FARMSTEAD_SHARE, WOOD_SHARE = 0.2, 0.2


def build_village(preset: CityPreset, seed: int) -> CityGeometry:
    rng = np.random.default_rng(seed)
    p = preset
    extent = district_extent(p)
    half = extent / 2
    built = Boxes()
    add = built.add
    parcels = torch.zeros(p.blocks, p.blocks, dtype=torch.long)

    farm = 0
    for bx in range(p.blocks):
        for by in range(p.blocks):
            x0 = -half + p.street_width + bx * (p.block_size + p.street_width)
            y0 = -half + p.street_width + by * (p.block_size + p.street_width)
            roll = rng.random()
            if roll < FARMSTEAD_SHARE:
                farm += 1
                add_farmstead(rng, p, x0, y0, farm, add)
            elif roll < FARMSTEAD_SHARE + WOOD_SHARE:
                for _ in range(int(rng.integers(8, 20))):
                    xy = np.array([x0, y0]) + rng.uniform(3.0, p.block_size - 3.0, 2)
                    add_tree(rng, p, xy, add)
            else:
                parcels[bx, by] = int(rng.choice([MEADOW, WHEAT, YOUNG_CROP, PLOUGHED]))
                if rng.random() < 0.5:  # a lone tree at a field's corner
                    corner = np.array([x0, y0]) + rng.choice([1.5, p.block_size - 1.5], 2)
                    add_tree(rng, p, corner, add)
            add_hedges(rng, p, x0, y0, add)
    return built.geometry(p, parcels)


def add_tree(rng, p: CityPreset, xy: np.ndarray, add) -> None:
    """A trunk and a canopy of two boxes, the upper one narrower: 6 to 14 m tall."""
    trunk = rng.uniform(1.8, 3.5)
    width = rng.uniform(3.0, 6.5)
    lower, upper = rng.uniform(2.5, 5.0), rng.uniform(1.5, 4.0)
    bark = [0.3, 0.22, 0.15]
    leaf = (np.array([0.2, 0.38, 0.14]) + rng.uniform(-0.06, 0.08, 3)).clip(0.05, 0.6).tolist()
    add([xy[0] - 0.25, xy[1] - 0.25, 0.0], [xy[0] + 0.25, xy[1] + 0.25, trunk], TRUNK, bark, -1)
    w = width / 2
    add([xy[0] - w, xy[1] - w, trunk], [xy[0] + w, xy[1] + w, trunk + lower], CANOPY, leaf, -1)
    w *= rng.uniform(0.5, 0.7)
    top = trunk + lower
    add([xy[0] - w, xy[1] - w, top], [xy[0] + w, xy[1] + w, top + upper], CANOPY, leaf, -1)


def add_farmstead(rng, p: CityPreset, x0: float, y0: float, owner: int, add) -> None:
    """A house (maybe with a wing), a long barn, sometimes a silo, and trees round the yard."""
    lot = p.block_size
    wall = (np.array([0.82, 0.76, 0.62]) + rng.uniform(-0.1, 0.08, 3)).clip(0.3, 0.95).tolist()
    corner = np.array([x0, y0]) + rng.uniform(2.0, 6.0, 2)
    size = rng.uniform([8.0, 6.0], [12.0, 9.0])
    height = rng.uniform(5.0, 8.0)
    add([*corner, 0.0], [*(corner + size), height], BUILDING, wall, owner)
    if rng.random() < 0.5:  # a lower wing
        wing = np.array([corner[0] + size[0], corner[1]])
        add(
            [*wing, 0.0],
            [wing[0] + 4.0, wing[1] + size[1] * 0.6, height * 0.6],
            BUILDING,
            wall,
            owner,
        )
    barn_colour = (np.array([0.55, 0.22, 0.15]) + rng.uniform(-0.08, 0.08, 3)).clip(0.1, 0.8)
    barn_size = rng.uniform([14.0, 8.0], [20.0, 11.0])
    barn = np.array([x0 + lot - 2.0 - barn_size[0], y0 + lot - 2.0 - barn_size[1]])
    add(
        [*barn, 0.0],
        [*(barn + barn_size), rng.uniform(6.0, 10.0)],
        BUILDING,
        barn_colour.tolist(),
        owner,
    )
    if rng.random() < 0.35:  # a silo: the tallest thing for a kilometre
        s = np.array([barn[0] - 4.5, barn[1] + 1.0])
        add(
            [*s, 0.0],
            [*(s + 3.0), p.max_height * rng.uniform(0.7, 1.0)],
            MAST,
            [0.72, 0.72, 0.7],
            owner,
        )
    for _ in range(int(rng.integers(2, 6))):
        xy = np.array([x0, y0]) + rng.choice(
            [rng.uniform(1.5, 4.0), rng.uniform(lot - 4.0, lot - 1.5)], 2
        )
        add_tree(rng, p, xy, add)


def add_hedges(rng, p: CityPreset, x0: float, y0: float, add) -> None:
    """Hedgerows along some of a parcel's south and west edges, with a gate gap."""
    green = [0.17, 0.3, 0.12]
    for axis in (0, 1):
        if rng.random() >= 0.4:
            continue
        height = rng.uniform(1.2, 2.2)
        gap = rng.uniform(4.0, p.block_size - 8.0)
        for start, end in ((0.0, gap), (gap + 4.0, p.block_size)):
            lo = np.array([x0, y0], dtype=np.float64)
            hi = lo.copy()
            lo[axis] += start
            hi[axis] += end
            hi[1 - axis] += 1.0
            add([*lo, 0.0], [*hi, height], HEDGE, green, -1)

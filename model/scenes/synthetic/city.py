"""Seeded procedural city district: axis-aligned boxes on a ground plane (z = 0), so truth is exact.

Frame: metres, x east, y north, z up; the district is centred on the origin.
"""

from __future__ import annotations

import numpy as np

from model.scenes.synthetic.geometry import (
    BUILDING,
    KIOSK,
    MAST,
    POLE,
    Boxes,
    CityGeometry,
    district_extent,
)
from model.scenes.synthetic.presets import CityPreset


def build_streets(preset: CityPreset, seed: int) -> CityGeometry:
    rng = np.random.default_rng(seed)
    p = preset
    extent = district_extent(p)
    half = extent / 2
    built = Boxes()
    add = built.add
    building = 0
    for bx in range(p.blocks):
        for by in range(p.blocks):
            x0 = -half + p.street_width + bx * (p.block_size + p.street_width)
            y0 = -half + p.street_width + by * (p.block_size + p.street_width)
            lots = int(rng.integers(1, 3))  # 1 or 2 lots per side
            lot = p.block_size / lots
            for lx in range(lots):
                for ly in range(lots):
                    if rng.random() < 0.15:
                        continue  # an empty lot: a plaza
                    building += 1
                    add_building(rng, p, x0 + lx * lot, y0 + ly * lot, lot, building, add)
    add_street_furniture(rng, p, half, add)
    return built.geometry(p)


def add_building(rng, p: CityPreset, x0: float, y0: float, lot: float, owner: int, add) -> None:
    """A main box on an inset footprint, maybe an L-wing, a setback tier and a roof mast."""
    inset = rng.uniform(0.8, 2.5, size=4)
    lo = np.array([x0 + inset[0], y0 + inset[1]])
    hi = np.array([x0 + lot - inset[2], y0 + lot - inset[3]])
    tower = rng.random() < 0.12
    height = (
        p.max_height * rng.uniform(0.75, 1.0)
        if tower
        else min(p.max_height * 0.6, rng.lognormal(np.log(p.max_height * 0.25), 0.4))
    )
    height = float(max(4.0, height))
    colour = (np.array([0.55, 0.5, 0.45]) + rng.uniform(-0.2, 0.25, 3)).clip(0.15, 0.9).tolist()
    size = hi - lo
    if rng.random() < 0.4 and not tower:  # L-shape: cut the main box and add a lower or higher wing
        axis = int(rng.integers(0, 2))
        cut = lo[axis] + size[axis] * rng.uniform(0.45, 0.65)
        wing_hi = hi.copy()
        wing_hi[1 - axis] = lo[1 - axis] + size[1 - axis] * rng.uniform(0.4, 0.6)
        main_hi = hi.copy()
        main_hi[axis] = cut
        add([*lo, 0.0], [*main_hi, height], BUILDING, colour, owner)
        wing_lo = lo.copy()
        wing_lo[axis] = cut
        add(
            [*wing_lo, 0.0],
            [*wing_hi, max(4.0, height * rng.uniform(0.5, 1.4))],
            BUILDING,
            colour,
            owner,
        )
    else:
        add([*lo, 0.0], [*hi, height], BUILDING, colour, owner)
    if rng.random() < 0.35 or tower:  # setback tier
        shrink = size * rng.uniform(0.15, 0.3, 2)
        tier = height * rng.uniform(0.15, 0.4)
        add([*(lo + shrink), height], [*(hi - shrink), height + tier], BUILDING, colour, owner)
        height += tier
    if rng.random() < 0.3:  # a thin mast on the roof
        c = lo + size * rng.uniform(0.3, 0.7, 2)
        add(
            [c[0] - 0.2, c[1] - 0.2, height],
            [c[0] + 0.2, c[1] + 0.2, height + rng.uniform(3.0, 8.0)],
            MAST,
            [0.7, 0.7, 0.72],
            owner,
        )


def add_street_furniture(rng, p: CityPreset, half: float, add) -> None:
    """Street-light poles along the streets and a few kiosks: thin and small structures."""
    spacing = 15.0
    for line in range(p.blocks + 1):
        centre = -half + line * (p.block_size + p.street_width) + p.street_width / 2
        edge = centre + p.street_width / 2 - 0.8  # on the sidewalk
        for s in np.arange(-half + spacing / 2, half, spacing):
            jitter = rng.uniform(-1.0, 1.0)
            for x, y in ((s + jitter, edge), (edge, s + jitter)):
                add(
                    [x - 0.15, y - 0.15, 0.0],
                    [x + 0.15, y + 0.15, 6.0],
                    POLE,
                    [0.35, 0.35, 0.38],
                    -1,
                )
        if rng.random() < 0.5:
            s = rng.uniform(-half + 5, half - 5)
            add(
                [s - 1.0, centre - p.street_width / 2 + 0.2, 0.0],
                [s + 1.0, centre - p.street_width / 2 + 2.0, 2.5],
                KIOSK,
                rng.uniform(0.3, 0.95, 3).tolist(),
                -1,
            )

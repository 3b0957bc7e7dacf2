"""Materials, sunlight with hard shadows, and the sky. Colours are linear RGB in [0, 1]."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from model.scenes.synthetic.geometry import BUILDING, CANOPY, HEDGE, KIOSK, CityGeometry
from model.scenes.synthetic.raycast import GROUND, SKY, raycast
from model.scenes.synthetic.village import PLOUGHED, WHEAT, YOUNG_CROP

SUN = torch.tensor(
    [
        math.cos(math.radians(40)) * math.cos(math.radians(135)),
        math.cos(math.radians(40)) * math.sin(math.radians(135)),
        math.sin(math.radians(40)),
    ],
    dtype=torch.float64,
)
SUN_COLOUR = torch.tensor([1.0, 0.95, 0.85])
SKY_AMBIENT = torch.tensor([0.55, 0.62, 0.75])


def hash_noise(ijk: Tensor, salt: int = 0) -> Tensor:
    """Deterministic per-cell noise in [0, 1) from integer lattice coordinates."""
    h = (
        (ijk[..., 0] * 73856093)
        ^ (ijk[..., 1] * 19349663)
        ^ (ijk[..., 2] * 83492791)
        ^ (salt * 2654435761)
    )
    h = (h ^ (h >> 13)) * 1274126177
    return ((h ^ (h >> 16)) & 0xFFFF).float() / 65536.0


def lattice(points: Tensor, scale: float) -> Tensor:
    return torch.floor(points / scale).long()


def sky(dirs: Tensor) -> Tensor:
    up = dirs[:, 2].clamp(-1, 1).float()[:, None]
    horizon, zenith = torch.tensor([0.82, 0.87, 0.93]), torch.tensor([0.28, 0.48, 0.82])
    base = horizon + (zenith - horizon) * up.clamp(min=0).sqrt()
    glow = (dirs.float() @ SUN.float()).clamp(min=0)[:, None] ** 200
    return (base + 0.8 * glow * SUN_COLOUR).clamp(0, 1)


def ground_albedo(p: Tensor, geometry: CityGeometry) -> Tensor:
    """The ground's colour under each point, by the preset's layout."""
    if geometry.parcels is not None:
        return village_ground_albedo(p, geometry)
    return city_ground_albedo(p, geometry)


def outer_fields(p: Tensor) -> Tensor:
    """Farmland beyond the district, out to the horizon: 20 m patches of varied hue."""
    fine = hash_noise(lattice(p, 0.35), 1)[:, None]
    field = (
        torch.tensor([0.45, 0.42, 0.22])
        + torch.tensor([-0.2, 0.05, -0.05]) * hash_noise(lattice(p, 20.0), 3)[:, None]
    )
    return field * (0.85 + 0.3 * fine)


def village_ground_albedo(p: Tensor, geometry: CityGeometry) -> Tensor:
    """Crops in rows (wheat, young crop, ploughed furrows) or meadow per parcel, grass lanes between
    them, a dirt road along the middle lane, farmland beyond."""
    pr, parcels = geometry.preset, geometry.parcels
    assert parcels is not None
    half = geometry.extent / 2
    period = pr.block_size + pr.street_width
    x, y = p[:, 0], p[:, 1]
    sx, sy = torch.remainder(x + half, period), torch.remainder(y + half, period)
    inside = (x.abs() < half) & (y.abs() < half)
    lane = inside & ((sx < pr.street_width) | (sy < pr.street_width))
    i = torch.floor((x + half) / period).long().clamp(0, pr.blocks - 1)
    j = torch.floor((y + half) / period).long().clamp(0, pr.blocks - 1)
    code = parcels[i, j]
    fine = hash_noise(lattice(p, 0.3), 6)[:, None]
    patch = hash_noise(lattice(p, 3.0), 7)[:, None]
    # rows run along x or y, by parcel
    along_x = hash_noise(torch.stack([i, j, torch.zeros_like(i)], -1), 8) < 0.5
    rows = torch.where(along_x, torch.remainder(y, 1.6), torch.remainder(x, 1.6)) < 0.7
    row_shade = torch.where(rows, 0.75, 1.1)[:, None]
    meadow = torch.tensor([0.3, 0.48, 0.2]) * (0.75 + 0.5 * fine) * (0.85 + 0.3 * patch)
    wheat = torch.tensor([0.66, 0.56, 0.28]) * row_shade * (0.9 + 0.2 * fine)
    young = torch.tensor([0.34, 0.52, 0.18]) * row_shade * (0.85 + 0.3 * fine)
    ploughed = torch.tensor([0.36, 0.26, 0.17]) * row_shade * (0.8 + 0.4 * fine)
    albedo = meadow
    for value, colour in ((WHEAT, wheat), (YOUNG_CROP, young), (PLOUGHED, ploughed)):
        albedo = torch.where((code == value)[:, None], colour, albedo)
    grass = torch.tensor([0.36, 0.5, 0.24]) * (0.8 + 0.4 * fine)
    albedo = torch.where(lane[:, None], grass, albedo)
    # the dirt road: 5 m down the middle of the middle lane running north
    middle = torch.floor((x + half) / period) == pr.blocks // 2
    road = inside & middle & ((sx - pr.street_width / 2).abs() < 2.5)
    dirt = torch.tensor([0.55, 0.47, 0.36]) * (0.85 + 0.3 * fine)
    albedo = torch.where(road[:, None], dirt, albedo)
    return torch.where(inside[:, None], albedo, outer_fields(p))


def city_ground_albedo(p: Tensor, geometry: CityGeometry) -> Tensor:
    """Streets (asphalt, lane dashes), sidewalks, plazas with grass inside blocks, fields
    outside."""
    pr = geometry.preset
    half = geometry.extent / 2
    period = pr.block_size + pr.street_width
    x, y = p[:, 0], p[:, 1]
    # Position within the street/block pattern: [0, street) is street, then the block.
    sx, sy = torch.remainder(x + half, period), torch.remainder(y + half, period)
    in_street_x, in_street_y = sx < pr.street_width, sy < pr.street_width
    inside = (x.abs() < half) & (y.abs() < half)
    street = inside & (in_street_x | in_street_y)
    near_edge = (torch.minimum(sx, period - sx) < 2.5) | (torch.minimum(sy, period - sy) < 2.5)
    sidewalk = inside & ~street & near_edge
    fine = hash_noise(lattice(p, 0.35), 1)[:, None]
    coarse = hash_noise(lattice(p, 7.0), 2)[:, None]
    asphalt = torch.tensor([0.22, 0.22, 0.24]) * (0.85 + 0.3 * fine)
    pavement = torch.tensor([0.58, 0.56, 0.52]) * (0.8 + 0.4 * fine)
    grass = torch.tensor([0.25, 0.45, 0.18]) * (0.7 + 0.6 * fine) * (0.85 + 0.3 * coarse)
    albedo = torch.where(inside[:, None], grass, outer_fields(p))
    albedo = torch.where(sidewalk[:, None], pavement, albedo)
    albedo = torch.where(street[:, None], asphalt, albedo)
    # Dashed lane markings on street centre lines.
    centre_x = (sx - pr.street_width / 2).abs() < 0.2
    centre_y = (sy - pr.street_width / 2).abs() < 0.2
    dash_y = torch.remainder(y, 4.0) < 2.0
    dash_x = torch.remainder(x, 4.0) < 2.0
    marking = inside & (
        (centre_x & in_street_x & ~in_street_y & dash_y)
        | (centre_y & in_street_y & ~in_street_x & dash_x)
    )
    return torch.where(marking[:, None], torch.tensor([0.9, 0.9, 0.85]), albedo)


def box_albedo(p: Tensor, normal: Tensor, box: Tensor, geometry: CityGeometry) -> Tensor:
    """Facades with window grids, textured roofs, plain metal for masts and poles, bright kiosks."""
    base = geometry.colour[box]
    kind = geometry.kind[box]
    fine = hash_noise(lattice(p, 0.4), 4)[:, None]
    roof = normal[:, 2] > 0.5
    # Facade coordinate along the wall: x on walls facing +-y, y on walls facing +-x.
    along = torch.where(normal[:, 0].abs() > 0.5, p[:, 1], p[:, 0])
    wu, wv = torch.remainder(along, 3.0), torch.remainder(p[:, 2], 3.2)
    window = (wu > 0.7) & (wu < 2.3) & (wv > 0.9) & (wv < 2.5) & (p[:, 2] > 1.0)
    lit = hash_noise(
        torch.stack(
            [
                torch.floor(along / 3.0).long(),
                torch.floor(p[:, 2] / 3.2).long(),
                geometry.building[box],
            ],
            -1,
        ),
        5,
    )[:, None]
    glass = torch.tensor([0.12, 0.16, 0.24]) + 0.25 * (lit > 0.85).float() * torch.tensor(
        [0.9, 0.8, 0.4]
    )
    facade = torch.where(window[:, None], glass, base * (0.85 + 0.3 * fine))
    roof_colour = (0.55 * base + 0.2) * (0.75 + 0.5 * fine)
    albedo = torch.where(roof[:, None], roof_colour, facade)
    albedo = torch.where((kind == BUILDING)[:, None], albedo, base * (0.9 + 0.2 * fine))
    # Foliage: leaves and gaps at 0.25 m, darker clumps at 1.5 m.
    leaves = hash_noise(lattice(p, 0.25), 9)[:, None]
    clumps = hash_noise(lattice(p, 1.5), 10)[:, None]
    foliage = base * (0.55 + 0.7 * leaves) * (0.75 + 0.4 * clumps)
    albedo = torch.where(((kind == CANOPY) | (kind == HEDGE))[:, None], foliage, albedo)
    return torch.where((kind == KIOSK)[:, None], base, albedo)


def shade(geometry: CityGeometry, origins: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
    """Colour (linear RGB) and depth (t, inf for sky) of each ray."""
    t, hit, normal = raycast(geometry, origins, dirs)
    colour = sky(dirs)
    surface = hit != SKY
    idx = torch.nonzero(surface).squeeze(1)
    p = origins[idx] + dirs[idx] * t[idx, None]
    n = normal[idx]
    albedo = torch.empty(len(idx), 3)
    on_ground = hit[idx] == GROUND
    albedo[on_ground] = ground_albedo(p[on_ground], geometry)
    on_box = ~on_ground
    albedo[on_box] = box_albedo(p[on_box], n[on_box], hit[idx][on_box] - 1, geometry)
    cos_sun = (n @ SUN).clamp(min=0)
    facing = torch.nonzero(cos_sun > 0).squeeze(1)
    sunlit = torch.zeros(len(idx), dtype=torch.bool)
    if len(facing):
        start = p[facing] + n[facing] * 1e-4
        shadow_t, _, _ = raycast(geometry, start, SUN.expand(len(facing), 3))
        sunlit[facing] = torch.isinf(shadow_t)
    # Sky light is dimmer on walls than on open ground and roofs (they see half the sky).
    ambient = SKY_AMBIENT * (0.35 + 0.15 * n[:, 2].clamp(min=0)).float()[:, None]
    direct = SUN_COLOUR * (0.85 * cos_sun * sunlit).float()[:, None]
    colour[idx] = (albedo * (ambient + direct)).clamp(0, 1)
    return colour, t

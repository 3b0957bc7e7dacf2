"""What every synthetic layout builds: axis-aligned boxes on a ground plane (z = 0), each of a kind
that picks its material, so depth and occupancy are exact.

Frame: metres, x east, y north, z up; the scene is centred on the origin.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from model.scenes.synthetic.presets import CityPreset

# Box kinds (they pick the material).
BUILDING, MAST, POLE, KIOSK = 1, 2, 3, 4
TRUNK, CANOPY, HEDGE = 5, 6, 7
KIND_NAMES = {
    BUILDING: "building",
    MAST: "mast",
    POLE: "pole",
    KIOSK: "kiosk",
    TRUNK: "trunk",
    CANOPY: "canopy",
    HEDGE: "hedge",
}


@dataclass
class CityGeometry:
    boxes: Tensor  # (K, 2, 3) float64: min, max corners in metres
    kind: Tensor  # (K,) int64: BUILDING | MAST | POLE | KIOSK
    colour: Tensor  # (K, 3) float32 base albedo
    building: Tensor  # (K,) int64: which building a box belongs to (-1 for street furniture)
    extent: float  # the district spans [-extent/2, extent/2]^2
    preset: CityPreset
    # per parcel of the layout grid (blocks x blocks, i east, j north): what covers its ground
    # (a layout's own codes; None: the city's streets and blocks)
    parcels: Tensor | None = None

    @property
    def top(self) -> float:
        return float(self.boxes[:, 1, 2].max())


class Boxes:
    """The boxes a layout adds one by one, then its CityGeometry."""

    def __init__(self) -> None:
        self.boxes: list = []
        self.kinds: list[int] = []
        self.colours: list = []
        self.owners: list[int] = []

    def add(self, lo, hi, kind: int, colour, owner: int) -> None:
        self.boxes.append([lo, hi])
        self.kinds.append(kind)
        self.colours.append(colour)
        self.owners.append(owner)

    def geometry(self, p: CityPreset, parcels: Tensor | None = None) -> CityGeometry:
        return CityGeometry(
            boxes=torch.tensor(self.boxes, dtype=torch.float64),
            kind=torch.tensor(self.kinds, dtype=torch.long),
            colour=torch.tensor(self.colours, dtype=torch.float32),
            building=torch.tensor(self.owners, dtype=torch.long),
            extent=district_extent(p),
            preset=p,
            parcels=parcels,
        )


def district_extent(p: CityPreset) -> float:
    """Side of the square district: `blocks` blocks (or parcels) and the streets (or lanes) between
    and around them."""
    return p.blocks * p.block_size + (p.blocks + 1) * p.street_width

"""The one in-memory scene representation every later stage reads, whatever format it came from.

Frames (see docs/SCENES.md):
- source frame: the dataset's own coordinates (metres for Mega-NeRF and the synthetic city);
- world frame: right-handed, z up, normalised so that the automatic foreground box is centred at the
  origin with its longest side spanning [-1, 1]:  world = (axes @ source - origin) / scale.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from model.scenes.cameras import Cameras
from model.scenes.pixel_cache import PixelCache


@dataclass
class Views:
    """The images of one split with their cameras. Depth (ground truth, optional) is the distance
    along the unit ray from the camera centre in world units; +inf where the ray sees no surface.

    Loaded scenes decode an image (or depth map) only when it is indexed (`images` is a LazyFrames).
    Once a pixel cache is attached (`cache`), `image(i)` and every PixelTable of these views read
    from it."""

    names: list[str]
    images: Sequence[Tensor]  # uint8 (H, W, 3) each
    cameras: Cameras
    appearance: Tensor  # (N,) int64: the per-image appearance-embedding index, unique across splits
    depth: Sequence[Tensor] | None = None  # float32 (H, W) each
    # this split's decoded pixels on disk, when a worker attached them
    cache: PixelCache | None = None

    def __len__(self) -> int:
        return len(self.names)

    def image(self, index: int) -> Tensor:
        """uint8 (H, W, 3): from the pixel cache when one is attached, else decoded from its
        file."""
        return self.cache.image(index) if self.cache is not None else self.images[index]

    @property
    def num_pixels(self) -> int:
        return int((self.cameras.width * self.cameras.height).sum())


@dataclass(frozen=True)
class Normalization:
    """world = (axes @ source - origin) / scale; `scale` is source units per world unit."""

    axes: Tensor  # (3, 3) rotation taking source axes to a z-up frame (identity when unknown)
    origin: Tensor  # (3,) float64, in rotated source units (large at city scale)
    scale: float
    units: str  # "metres" when the source frame is metric, else "source units"

    def to_world(self, points: Tensor) -> Tensor:
        return (points.double() @ self.axes.double().T - self.origin.double()) / self.scale

    def to_source(self, points: Tensor) -> Tensor:
        return (points.double() * self.scale + self.origin.double()) @ self.axes.double()


@dataclass(frozen=True)
class Bounds:
    """The automatic foreground box (world frame) and how it was found."""

    aabb: Tensor  # (2, 3): min, max
    source: str  # which evidence set it: gt_depth | sparse_points | llff_bounds | camera_axes
    num_points: int  # evidence points used after filtering


@dataclass
class GroundTruthOccupancy:
    """Ground-truth occupancy: `occupied[i, j, k]` covers world box aabb_min + cell * [i, i+1] x
    ..."""

    occupied: Tensor  # bool (X, Y, Z)
    aabb: Tensor  # (2, 3) world frame

    @property
    def resolution(self) -> tuple[int, int, int]:
        x, y, z = self.occupied.shape
        return x, y, z

    @property
    def cell_size(self) -> Tensor:
        return (self.aabb[1] - self.aabb[0]) / torch.tensor(
            self.occupied.shape, dtype=self.aabb.dtype
        )

    @property
    def occupied_fraction(self) -> float:
        return float(self.occupied.float().mean())

    def lookup(self, points: Tensor) -> Tensor:
        """Occupancy at world points; points outside the grid read as free."""
        # the estimator interface takes points on any device
        points = points.to(self.occupied.device)
        ijk = torch.floor(
            (points.double() - self.aabb[0].double()) / self.cell_size.double()
        ).long()
        shape = torch.tensor(self.occupied.shape)
        inside = ((ijk >= 0) & (ijk < shape)).all(dim=-1)
        ijk = torch.minimum(ijk.clamp(min=0), shape - 1)
        return self.occupied[ijk[:, 0], ijk[:, 1], ijk[:, 2]] & inside


@dataclass
class Scene:
    format: str  # meganerf | nerfstudio | blender | llff | colmap
    root: Path
    splits: dict[str, Views]  # always "train"; "val" and "test" when the dataset has them
    normalization: Normalization
    bounds: Bounds
    downscale: int = 1
    occupancy: GroundTruthOccupancy | None = None
    points: Tensor | None = None  # sparse points (world frame) when the dataset ships them
    extras: dict = field(default_factory=dict)  # format-specific facts shown by `leco scene info`

    @property
    def train(self) -> Views:
        return self.splits["train"]

    @property
    def num_images(self) -> int:
        return sum(len(v) for v in self.splits.values())

    @property
    def has_depth(self) -> bool:
        return any(v.depth is not None for v in self.splits.values())

"""What a format reader hands over before normalisation: cameras in the dataset's units, already
turned into the z-up / OpenGL-camera convention, plus whatever geometric evidence the dataset
carries."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
from torch import Tensor

from model.scenes import values
from model.scenes.cameras import Cameras, make_cameras, rotation_error
from model.scenes.errors import SceneError
from model.scenes.frames import frames


@dataclass
class SourceSplit:
    names: list[str]
    # uint8 (H, W, 3), already downscaled; a LazyFrames: decoded when indexed
    images: Sequence[Tensor]
    cameras: Cameras  # positions in source units (rotated by SourceScene.axes)
    # float32 (H, W), source units, +inf = no surface; lazy too
    depth: Sequence[Tensor] | None = None


@dataclass
class SourceScene:
    format: str
    root: Path
    splits: dict[str, SourceSplit]
    axes: Tensor  # (3, 3) rotation the reader applied to reach a z-up frame (identity when unknown)
    units: str
    downscale: int
    points: Tensor | None = None  # evidence points (rotated source frame)
    points_kind: str | None = None  # sparse_points | llff_bounds
    occupied: Tensor | None = None  # bool (X, Y, Z) ground-truth occupancy grid
    occupancy_aabb: Tensor | None = None  # (2, 3) rotated source frame
    extras: dict = field(default_factory=dict)


POSE_TOLERANCE = 1e-3


def check_pose(path: Path, c2w: Tensor, where: str = "") -> None:
    """Refuse non-finite, far-off or non-rigid camera-to-world matrices, naming the file (and
    frame)."""
    if c2w.shape[-2:] != (3, 4):
        raise SceneError(
            path, f"camera pose{where} must be 3x4 (or 4x4), got shape {tuple(c2w.shape)}"
        )
    if not torch.isfinite(c2w).all():
        raise SceneError(path, f"camera pose{where} has non-finite values (NaN or Inf)")
    if bool((c2w[..., 3].abs() > values.MAX_COORDINATE).any()):
        raise SceneError(
            path, f"camera position{where} is beyond +-{values.MAX_COORDINATE:g} source units"
        )
    err = float(rotation_error(c2w.reshape(1, 3, 4))[0])
    if err > POSE_TOLERANCE:
        raise SceneError(
            path,
            f"camera pose{where} is not rigid: its rotation is not orthonormal with det +1 (error "
            f"{err:.3g})",
        )


Frame = Tensor | Callable[[], Tensor]  # a decoded tensor, or a loader that decodes it when called


class SplitBuilder:
    """Collects one split's views as a reader finds them; `build` stacks them into a SourceSplit.
    Images and depth maps may be loaders (an ImageFile) with their decoded (height, width) given as
    `size`."""

    def __init__(self) -> None:
        self.names: list[str] = []
        self.images: list[Frame] = []
        self.depth: list[Frame] = []
        self._sizes: list[tuple[int, int]] = []
        self._intrinsics: list[Tensor] = []
        self._c2w: list[Tensor] = []
        self._distortion: list[Tensor] = []

    def add(
        self,
        name: str,
        image: Frame,
        intrinsics: Tensor,
        c2w: Tensor,
        distortion: Tensor | None = None,
        depth: Frame | None = None,
        size: tuple[int, int] | None = None,
        *,
        source: Path,
        where: str = "",
    ) -> None:
        """One view; `source` is the file that describes its camera (and `where` the frame or row in
        it), named when the camera is refused: every view's camera is checked here, whatever format
        it came from."""
        if size is None:
            if not isinstance(image, Tensor):  # a loader's size is known only by decoding it
                raise TypeError(f"view {name!r}: an image given as a loader needs its decoded size")
            size = (image.shape[0], image.shape[1])
        intrinsics = torch.as_tensor(intrinsics, dtype=torch.float64).reshape(4)
        c2w = torch.as_tensor(c2w, dtype=torch.float64).reshape(3, 4)
        values.check_intrinsics(source, intrinsics, size[1], size[0], where)
        check_pose(source, c2w, where)
        distortion = (
            torch.zeros(4) if distortion is None else values.distortion(source, distortion, where)
        )
        self.names.append(name)
        self.images.append(image)
        self._sizes.append(size)
        self._intrinsics.append(intrinsics)
        self._c2w.append(c2w)
        self._distortion.append(distortion.float())
        if depth is not None:
            self.depth.append(depth)

    def build(self) -> SourceSplit:
        n = len(self.names)
        cameras = make_cameras(
            torch.stack(self._intrinsics) if n else torch.zeros(0, 4),
            torch.stack(self._c2w) if n else torch.zeros(0, 3, 4),
            torch.tensor([w for _, w in self._sizes], dtype=torch.long),
            torch.tensor([h for h, _ in self._sizes], dtype=torch.long),
            torch.stack(self._distortion) if n else torch.zeros(0, 4),
        )
        return SourceSplit(
            self.names, frames(self.images), cameras, frames(self.depth) if self.depth else None
        )


def scale_intrinsics(intrinsics: Tensor, size: tuple[int, int], width: int, height: int) -> Tensor:
    """Intrinsics for an image of `size` (height, width) resized from width x height."""
    sx, sy = size[1] / width, size[0] / height
    fx, fy, cx, cy = torch.as_tensor(intrinsics, dtype=torch.float64).reshape(4).tolist()
    return torch.tensor([fx * sx, fy * sy, cx * sx, cy * sy], dtype=torch.float64)


def up_alignment(c2w: Tensor) -> Tensor:
    """Rotation taking the mean camera up vector to +z: the world convention for formats whose files
    do not say which way is up (LLFF, nerfstudio)."""
    up = c2w[:, :, 1].double().mean(dim=0)
    a = up / up.norm().clamp(min=1e-12)
    b = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    v, c = torch.linalg.cross(a, b), float(a @ b)
    if c < -1 + 1e-9:  # upside down: half a turn about x
        return torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    vx = torch.tensor([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + vx + vx @ vx / (1 + c)


def rotate_source(source: SourceScene, rotation: Tensor) -> SourceScene:
    """Apply a world rotation to every camera and point of a reader's output (before
    normalisation)."""
    r = rotation.double()
    for split in source.splits.values():
        split.cameras = replace(split.cameras, c2w=r @ split.cameras.c2w.double())
    if source.points is not None:
        source.points = source.points.double() @ r.T
    source.axes = (r @ source.axes.double()).float()
    return source

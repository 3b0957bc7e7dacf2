"""From a reader's SourceScene to the normalised Scene: automatic bounds, then the world frame."""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from model.scenes.bounds import foreground_aabb
from model.scenes.errors import SceneError
from model.scenes.frames import frames
from model.scenes.scene import Bounds, GroundTruthOccupancy, Normalization, Scene, Views
from model.scenes.source import SourceScene

SPLIT_ORDER = ("train", "val", "test")


def build_scene(source: SourceScene) -> Scene:
    if not source.splits.get("train") or len(source.splits["train"].names) == 0:
        raise SceneError(source.root, "the train split is empty: no training images were found")
    aabb, kind, num_points = foreground_aabb(source)
    aabb = aabb.double()
    origin = 0.5 * (aabb[0] + aabb[1])
    scale = float(0.5 * (aabb[1] - aabb[0]).max())
    norm = Normalization(axes=source.axes.float(), origin=origin, scale=scale, units=source.units)

    splits: dict[str, Views] = {}
    next_appearance = 0
    for name in sorted(
        source.splits, key=lambda s: SPLIT_ORDER.index(s) if s in SPLIT_ORDER else 99
    ):
        split = source.splits[name]
        if len(split.names) == 0:
            continue
        # subtract the origin in float64: city coordinates are large
        c2w = split.cameras.c2w.double().clone()
        c2w[:, :, 3] = (c2w[:, :, 3] - origin) / scale
        c2w = c2w.float()
        appearance = torch.arange(next_appearance, next_appearance + len(split.names))
        next_appearance += len(split.names)
        depth = None if split.depth is None else frames(split.depth).map(_Divide(scale))
        splits[name] = Views(
            split.names, split.images, replace(split.cameras, c2w=c2w), appearance, depth
        )

    occupancy = None
    if source.occupied is not None:
        if source.occupancy_aabb is None:  # readers give the grid and the box it covers together
            raise SceneError(
                source.root, "a ground-truth occupancy grid came without its bounding box"
            )
        occupancy = GroundTruthOccupancy(
            source.occupied, ((source.occupancy_aabb.double() - origin) / scale).float()
        )
    points = (
        None
        if source.points is None
        else ((source.points.double() - origin.double()) / scale).float()
    )
    bounds = Bounds(aabb=((aabb - origin) / scale).float(), source=kind, num_points=num_points)
    return Scene(
        format=source.format,
        root=source.root,
        splits=splits,
        normalization=norm,
        bounds=bounds,
        downscale=source.downscale,
        occupancy=occupancy,
        points=points,
        extras=source.extras,
    )


class _Divide:
    """Depth in source units -> world units, as each map is read (a class, not a lambda:
    picklable)."""

    def __init__(self, scale: float):
        self.scale = scale

    def __call__(self, depth: Tensor) -> Tensor:
        return depth / self.scale

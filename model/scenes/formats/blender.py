"""Blender / NeRF-synthetic: transforms_{train,val,test}.json, RGBA images composited on a
background."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from model.scenes.errors import SceneError
from model.scenes.formats.jsonfile import field, frames, number, opengl_pose, read_json
from model.scenes.images import ImageFile, check_image_size, find_image, probe_image
from model.scenes.paths import named_file, scene_file
from model.scenes.source import SourceScene, SplitBuilder, scale_intrinsics


def load_blender(root: Path, downscale: int, background: tuple[float, float, float]) -> SourceScene:
    splits = {}
    size: tuple[int, int] | None = None
    for split in ("train", "val", "test"):
        path = root / f"transforms_{split}.json"
        if not path.is_file():
            continue
        scene_file(root, path)
        data = read_json(path)
        angle = number(path, data, "camera_angle_x")
        if not 0 < angle < math.pi:
            raise SceneError(path, f"camera_angle_x must be in (0, pi) radians, got {angle}")
        builder = SplitBuilder()
        for i, frame in enumerate(frames(path, data)):
            where = f" (frame {i})"
            image_path = scene_file(
                root,
                find_image(
                    named_file(
                        root, field(path, frame, "file_path", where), path, f"file_path{where}"
                    )
                ),
            )
            w, h = probe_image(image_path)
            size = size or (w, h)
            check_image_size(image_path, (w, h), *size)  # the format has one camera for all frames
            focal = 0.5 * w / math.tan(0.5 * angle)
            c2w = opengl_pose(path, frame, where)
            image = ImageFile(image_path, w, h, downscale, background)
            intrinsics = scale_intrinsics(
                torch.tensor([focal, focal, w / 2, h / 2]), image.size, w, h
            )
            builder.add(
                Path(image_path).stem,
                image,
                intrinsics,
                c2w,
                size=image.size,
                source=path,
                where=where,
            )
        if not builder.names:
            raise SceneError(path, "split has no frames")
        splits[split] = builder.build()
    if "train" not in splits:
        raise SceneError(root / "transforms_train.json", "train split file is missing")
    return SourceScene(
        format="blender",
        root=root,
        splits=splits,
        axes=torch.eye(3),  # Blender's world is already z up
        units="source units",
        downscale=downscale,
        extras={"background": list(background)},
    )

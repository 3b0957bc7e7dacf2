"""nerfstudio transforms.json: global or per-frame intrinsics, PINHOLE or OPENCV (k1, k2, p1,
p2)."""

from __future__ import annotations

from pathlib import Path

import torch

from model.scenes import values
from model.scenes.errors import SceneError
from model.scenes.formats.jsonfile import field, frames, number, opengl_pose, read_json
from model.scenes.formats.points import read_ply_points
from model.scenes.images import ImageFile, check_image_size, probe_image
from model.scenes.paths import named_file, scene_file
from model.scenes.source import (
    SourceScene,
    SplitBuilder,
    rotate_source,
    scale_intrinsics,
    up_alignment,
)

SUPPORTED_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV")
DISTORTION = ("k1", "k2", "p1", "p2")
# without explicit split lists, every 8th frame is held out (the LLFF/nerfstudio habit)
VAL_EVERY = 8


def frame_camera(
    path: Path, data: dict, frame: dict, where: str
) -> tuple[torch.Tensor, int, int, torch.Tensor]:
    """Intrinsics, size and distortion of one frame: per-frame values override the global ones."""
    merged = {**data, **frame}
    model = str(merged.get("camera_model", "OPENCV"))
    if model not in SUPPORTED_MODELS:
        raise SceneError(
            path,
            f"camera_model {model!r}{where} is not supported (use one of "
            f"{', '.join(SUPPORTED_MODELS)})",
        )
    fx = number(path, merged, "fl_x", where)
    fy = number(path, merged, "fl_y", where, default=fx)
    w, h = values.image_size(
        path, field(path, merged, "w", where), field(path, merged, "h", where), where
    )
    cx = number(path, merged, "cx", where, default=w / 2)
    cy = number(path, merged, "cy", where, default=h / 2)
    for extra in ("k3", "k4"):
        if abs(number(path, merged, extra, where, default=0.0)) > 0:
            raise SceneError(
                path,
                f"distortion term {extra}{where} is not supported (OPENCV k1, k2, p1, p2 only)",
            )
    distortion = values.distortion(
        path, [number(path, merged, k, where, default=0.0) for k in DISTORTION], where
    )
    if model != "OPENCV" and bool(distortion.any()):
        raise SceneError(
            path, f"camera_model {model}{where} has distortion terms; declare it OPENCV"
        )
    return torch.tensor([fx, fy, cx, cy], dtype=torch.float64), w, h, distortion


def split_of(path: Path, data: dict, file_path: str, index: int) -> str:
    """The split from nerfstudio's {train,val,test}_filenames lists when present, else every 8th is
    val."""
    lists = {
        s: data[f"{s}_filenames"] for s in ("train", "val", "test") if f"{s}_filenames" in data
    }
    for split, listed in lists.items():
        if not isinstance(listed, list) or not all(isinstance(p, str) for p in listed):
            raise SceneError(
                path,
                f"'{split}_filenames' must be a list of file paths, got {values.describe(listed)}",
            )
    if not lists:
        return "val" if index % VAL_EVERY == 0 else "train"
    key = Path(file_path).as_posix()
    for split, listed in lists.items():
        if key in {Path(p).as_posix() for p in listed}:
            return split
    return "unlisted"


def load_nerfstudio(root: Path, downscale: int) -> SourceScene:
    path = scene_file(root, root / "transforms.json")
    data = read_json(path)
    builders: dict[str, SplitBuilder] = {}
    for i, frame in enumerate(frames(path, data)):
        where = f" (frame {i})"
        named = field(path, frame, "file_path", where)
        intrinsics, w, h, distortion = frame_camera(path, data, frame, where)
        c2w = opengl_pose(path, frame, where)
        # refuses anything but a string
        image_path = named_file(root, named, path, f"file_path{where}")
        file_path = str(named)
        if not image_path.is_file():
            raise SceneError(image_path, f"image is missing (listed in {path.name}{where})")
        check_image_size(image_path, probe_image(image_path), w, h)
        image = ImageFile(image_path, w, h, downscale)
        split = split_of(path, data, file_path, i)
        if split != "unlisted":
            builders.setdefault(split, SplitBuilder()).add(
                Path(file_path).stem,
                image,
                scale_intrinsics(intrinsics, image.size, w, h),
                c2w,
                distortion,
                size=image.size,
                source=path,
                where=where,
            )
    if "train" not in builders:
        raise SceneError(
            path, "no training frames: 'frames' is empty or no frame is in the train split"
        )
    points = None
    if "ply_file_path" in data:
        ply = named_file(root, data["ply_file_path"], path, "ply_file_path")
        if not ply.is_file():
            raise SceneError(ply, "sparse point file named by 'ply_file_path' is missing")
        points = read_ply_points(ply)
    source = SourceScene(
        format="nerfstudio",
        root=root,
        splits={s: b.build() for s, b in builders.items()},
        axes=torch.eye(3),
        units="source units",
        downscale=downscale,
        points=points,
        points_kind="sparse_points" if points is not None else None,
    )
    all_c2w = torch.cat([s.cameras.c2w for s in source.splits.values()])
    return rotate_source(source, up_alignment(all_c2w))

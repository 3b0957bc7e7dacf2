"""LLFF: poses_bounds.npy (N x 17: 3x5 [R | t | hwf] + near, far) with images, images_N folders."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from model.scenes import values
from model.scenes.cameras import pixel_rays
from model.scenes.errors import SceneError
from model.scenes.folders import folder_factor
from model.scenes.formats.points import read_colmap_points
from model.scenes.images import IMAGE_SUFFIXES, ImageFile, probe_image
from model.scenes.limits import read_npy
from model.scenes.paths import scene_file
from model.scenes.source import SourceScene, SplitBuilder, rotate_source, up_alignment

VAL_EVERY = 8  # LLFF's usual hold-out: every 8th image


def image_folders(root: Path) -> dict[int, Path]:
    """Available image folders by downscale factor: images -> 1, images_N -> N."""
    found = {}
    for d in root.iterdir():
        m = re.fullmatch(r"images(?:_(\d+))?", d.name)
        if d.is_dir() and m:
            found[int(m.group(1) or 1)] = d
    return found


def pick_folder(root: Path, downscale: int | None) -> tuple[Path, int, int]:
    """(folder, its factor, extra factor to resize by) so that folder factor x extra = downscale."""
    folders = image_folders(root)
    if not folders:
        raise SceneError(
            root, "no image folder: expected images/ or images_N/ beside poses_bounds.npy"
        )
    if downscale is None:
        smallest = min(folders)
        return folders[smallest], smallest, 1
    factor = folder_factor(folders, downscale)
    if factor is None:
        have = ", ".join(folders[f].name for f in sorted(folders))
        raise SceneError(
            root,
            f"downscale {downscale} is not a multiple of any image folder's factor (have {have})",
        )
    return folders[factor], factor, downscale // factor


MAX_POSES = 100_000  # rows of poses_bounds.npy (one per image)


def load_llff(root: Path, downscale: int | None) -> SourceScene:
    path = scene_file(root, root / "poses_bounds.npy")
    array = read_npy(path, max_bytes=MAX_POSES * 17 * 8)
    if array.ndim != 2 or array.shape[1] != 17 or len(array) == 0:
        raise SceneError(path, f"must be an N x 17 array, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise SceneError(
            path,
            "has non-finite values in row(s) "
            f"{sorted(set(np.nonzero(~np.isfinite(array))[0].tolist()))}",
        )
    folder, factor, extra = pick_folder(root, downscale)
    files = sorted(scene_file(root, p) for p in folder.iterdir() if p.suffix in IMAGE_SUFFIXES)
    if len(files) != len(array):
        raise SceneError(
            folder, f"has {len(files)} images but poses_bounds.npy has {len(array)} poses"
        )

    poses = torch.from_numpy(array[:, :15].reshape(-1, 3, 5)).double()
    depth_bounds = torch.from_numpy(array[:, 15:17]).double()
    bad = torch.nonzero((depth_bounds[:, 0] <= 0) | (depth_bounds[:, 1] < depth_bounds[:, 0]))[:, 0]
    if len(bad):
        raise SceneError(
            path,
            "near/far depth bounds must satisfy 0 < near <= far, not in row(s) "
            f"{bad[:10].tolist()}",
        )
    builders = {"train": SplitBuilder(), "val": SplitBuilder()}
    for i, image_path in enumerate(files):
        where = f" (row {i})"
        h_full, w_full, focal = poses[i, :, 4].tolist()
        values.image_size(path, round(w_full), round(h_full), where)
        down, right, back, t = poses[i, :, 0], poses[i, :, 1], poses[i, :, 2], poses[i, :, 3]
        # LLFF [down, right, back] -> OpenGL [right, up, back]
        c2w = torch.stack([right, -down, back, t], dim=1)
        w, h = probe_image(image_path)
        if abs(w * factor - w_full) > factor or abs(h * factor - h_full) > factor:
            raise SceneError(
                image_path,
                f"image is {w}x{h} but poses_bounds.npy says {w_full:.0f}x{h_full:.0f} / {factor}",
            )
        image = ImageFile(image_path, w, h, extra)
        small_h, small_w = image.size
        s = small_w / w_full
        intrinsics = torch.tensor([focal * s, focal * s, small_w / 2, small_h / 2])
        split = "val" if i % VAL_EVERY == 0 else "train"
        builders[split].add(
            image_path.stem, image, intrinsics, c2w, size=image.size, source=path, where=where
        )
    splits = {name: b.build() for name, b in builders.items() if b.names}

    sparse = root / "sparse" / "0" / "points3D.bin"
    if sparse.is_file():
        # checked by the reader
        points, kind = read_colmap_points(scene_file(root, sparse)), "sparse_points"
    else:
        points, kind = bound_points(splits, depth_bounds, files), "llff_bounds"
    source = SourceScene(
        format="llff",
        root=root,
        splits=splits,
        axes=torch.eye(3),
        units="source units",
        downscale=factor * extra,
        points=points,
        points_kind=kind,
        extras={
            "image_folder": folder.name,
            "depth_bounds": [float(depth_bounds.min()), float(depth_bounds.max())],
        },
    )
    all_c2w = torch.cat([s.cameras.c2w for s in splits.values()])
    return rotate_source(source, up_alignment(all_c2w))


def bound_points(splits: dict, depth_bounds: torch.Tensor, files: list[Path]) -> torch.Tensor:
    """Points at each image's near and far z-depth on a 3x3 pixel grid: the evidence LLFF bounds
    give."""
    order = {p.stem: i for i, p in enumerate(files)}
    points = []
    for split in splits.values():
        cams = split.cameras
        for c, name in enumerate(split.names):
            w, h = float(cams.width[c]), float(cams.height[c])
            u, v = torch.meshgrid(
                torch.tensor([0.0, w / 2, w - 1]), torch.tensor([0.0, h / 2, h - 1]), indexing="ij"
            )
            o, d = pixel_rays(cams, torch.full((9,), c), u.reshape(-1), v.reshape(-1))
            cos = (d * cams.forward[c]).sum(-1, keepdim=True)  # z-depth -> distance along the ray
            for z in depth_bounds[order[name]].tolist():
                points.append(o.double() + d.double() * (z / cos.double()))
    return torch.cat(points)

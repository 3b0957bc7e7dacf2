"""Mega-NeRF format: coordinates.pt, {train,val}/metadata/*.pt, {train,val}/rgbs/*, plus the
synthetic city's optional gt/ folder (depth maps and an occupancy grid, in metres)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from model.scenes import values
from model.scenes.errors import SceneError
from model.scenes.images import (
    ImageFile,
    check_image_size,
    downscale_depth,
    find_image,
    probe_image,
)
from model.scenes.limits import (
    MAX_METADATA_BYTES,
    check_file_size,
    read_npy,
    read_npy_header,
    read_npz,
)
from model.scenes.paths import scene_file
from model.scenes.source import SourceScene, SourceSplit, SplitBuilder, scale_intrinsics

# Mega-NeRF's world is down-right-back (x down). DRB -> (east-like right, forward, up): a proper
# rotation.
DRB_TO_ZUP = torch.tensor(
    [[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]], dtype=torch.float64
)


def load_pt(path: Path) -> object:
    check_file_size(path, MAX_METADATA_BYTES, "a metadata file")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt or hostile pickles
        raise SceneError(
            path, f"cannot read this torch file ({exc.__class__.__name__}: {exc})"
        ) from None


def read_coordinates(root: Path) -> tuple[Tensor, float]:
    path = scene_file(root, root / "coordinates.pt")
    data = load_pt(path)
    if not isinstance(data, dict) or "origin_drb" not in data or "pose_scale_factor" not in data:
        raise SceneError(path, "must be a dict with 'origin_drb' and 'pose_scale_factor'")
    origin = values.array(path, data["origin_drb"], "origin_drb", ((3,),))
    scale = values.number(path, data["pose_scale_factor"], "pose_scale_factor", lo=1e-9)
    return origin, scale


def read_metadata(path: Path) -> dict:
    meta = load_pt(path)
    if not isinstance(meta, dict):
        raise SceneError(path, "metadata must be a dict with W, H, intrinsics and c2w")
    missing = [k for k in ("W", "H", "intrinsics", "c2w") if k not in meta]
    if missing:
        raise SceneError(path, f"metadata is missing field(s): {', '.join(missing)}")
    width, height = values.image_size(path, meta["W"], meta["H"])
    intrinsics = values.array(path, meta["intrinsics"], "intrinsics [fx, fy, cx, cy]", ((4,),))
    # the camera's checks: SplitBuilder.add
    c2w = values.array(path, meta["c2w"], "c2w", ((3, 4), (4, 4)))[:3]
    raw = meta.get("distortion")
    distortion = torch.zeros(4) if raw is None else values.distortion(path, raw)
    return {"W": width, "H": height, "intrinsics": intrinsics, "c2w": c2w, "distortion": distortion}


def check_depth_file(path: Path, height: int, width: int) -> None:
    """Present, with a float array of its image's size: the header only (the data is read when
    needed)."""
    if not path.is_file():
        raise SceneError(
            path, "ground-truth depth map is missing (gt/ exists, so every view needs one)"
        )
    dtype = read_npy_header(path, shape=(height, width))
    if dtype.kind != "f":
        raise SceneError(path, f"depth map must hold floats, not {dtype}")


def read_depth(path: Path, height: int, width: int) -> Tensor:
    # its image's size, checked before the data is read
    array = read_npy(path, shape=(height, width))
    if array.dtype.kind != "f":
        raise SceneError(path, f"depth map must hold floats, not {array.dtype}")
    depth = torch.from_numpy(array.astype(np.float32))
    if torch.isnan(depth).any() or (depth <= 0).any():
        raise SceneError(path, "depth map must be positive (inf for sky) with no NaN")
    return depth


class DepthFile:
    """A ground-truth depth map, read and downscaled when called."""

    def __init__(self, path: Path, height: int, width: int, factor: int):
        self.path, self.height, self.width, self.factor = path, height, width, factor

    def __call__(self) -> Tensor:
        return downscale_depth(read_depth(self.path, self.height, self.width), self.factor)


def read_split(
    root: Path, split: str, origin: Tensor, scale: float, downscale: int, with_depth: bool
) -> SourceSplit:
    meta_dir, rgb_dir = root / split / "metadata", root / split / "rgbs"
    builder = SplitBuilder()
    for meta_path in sorted(meta_dir.glob("*.pt")) if meta_dir.is_dir() else []:
        meta = read_metadata(scene_file(root, meta_path))
        image_path = scene_file(root, find_image(rgb_dir / meta_path.stem))
        check_image_size(image_path, probe_image(image_path), meta["W"], meta["H"])
        image = ImageFile(image_path, meta["W"], meta["H"], downscale)
        # DRB normalised -> metres, then rotate into the z-up frame; rotation keeps the camera axes'
        # roles.
        c2w = meta["c2w"].clone()
        c2w[:, 3] = origin + scale * c2w[:, 3]
        depth = None
        if with_depth:
            depth_path = scene_file(root, root / "gt" / "depth" / split / f"{meta_path.stem}.npy")
            check_depth_file(depth_path, meta["H"], meta["W"])
            depth = DepthFile(depth_path, meta["H"], meta["W"], downscale)
        intrinsics = scale_intrinsics(meta["intrinsics"], image.size, meta["W"], meta["H"])
        builder.add(
            meta_path.stem,
            image,
            intrinsics,
            DRB_TO_ZUP @ c2w,
            meta["distortion"],
            depth,
            image.size,
            source=meta_path,
        )
    return builder.build()


def read_occupancy(path: Path) -> tuple[Tensor, Tensor]:
    """Ground-truth grid -> (occupied, aabb) in the z-up metric frame. The file's world_from_grid
    maps grid coordinates to DRB metres; combined with DRB_TO_ZUP it must be an axis-aligned map."""
    arrays = read_npz(path)
    if "occupied" not in arrays or "world_from_grid" not in arrays:
        raise SceneError(path, "occupancy file needs arrays 'occupied' and 'world_from_grid'")
    occupied = torch.from_numpy(arrays["occupied"].astype(bool))
    m = DRB_TO_ZUP @ torch.from_numpy(arrays["world_from_grid"]).double()[:3]  # (3, 4): z-up metres
    linear, offset = m[:, :3], m[:, 3]
    if occupied.ndim != 3 or ((linear.abs() > 1e-9).sum(dim=0) != 1).any():
        raise SceneError(
            path,
            "occupancy grid must be 3-D and axis-aligned (world_from_grid a scaled permutation)",
        )
    world_axis = linear.abs().argmax(dim=0)  # grid axis a -> world axis
    signs = linear[world_axis, torch.arange(3)].sign()
    for a in range(3):
        if signs[a] < 0:
            occupied = occupied.flip(a)
    order = torch.argsort(world_axis)  # grid axis holding world x, y, z
    occupied = occupied.permute(*order.tolist()).contiguous()
    shape = torch.tensor(arrays["occupied"].shape, dtype=torch.float64)
    corners = torch.stack([offset, offset + linear @ shape])
    return occupied, torch.stack([corners.amin(0), corners.amax(0)])


MAX_GENERATOR_TEXT = 64
MAX_PRESET_FIELDS = 64


def short_text(path: Path, raw: object, name: str) -> str:
    if not isinstance(raw, str) or len(raw) > MAX_GENERATOR_TEXT:
        raise SceneError(
            path,
            f"{name} must be a string of at most {MAX_GENERATOR_TEXT} characters, got "
            f"{values.describe(raw)}",
        )
    return raw


def setting(path: Path, raw: object, name: str) -> object:
    """One generator setting: a boolean, a finite number or a short string."""
    if isinstance(raw, bool):
        return raw
    if isinstance(raw, str):
        return short_text(path, raw, name)
    value = values.number(path, raw, name)
    return int(value) if isinstance(raw, int) else value


def read_generator(path: Path) -> dict:
    """Which generator made a synthetic scene (generator, preset, seed), from its gt/scene.json: the
    only part of that file a scene's record keeps, typed and short."""
    check_file_size(path, MAX_METADATA_BYTES, "gt/scene.json")
    try:
        info = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(path, f"malformed JSON ({exc})") from None
    if not isinstance(info, dict):
        raise SceneError(path, f"must hold a JSON object, got {values.describe(info)}")
    generator: dict = {}
    if "generator" in info:
        generator["generator"] = short_text(path, info["generator"], "field 'generator'")
    if "preset" in info:
        preset = info["preset"]
        if not isinstance(preset, dict) or len(preset) > MAX_PRESET_FIELDS:
            raise SceneError(
                path,
                f"field 'preset' must be an object of at most {MAX_PRESET_FIELDS} settings, got "
                f"{values.describe(preset)}",
            )
        generator["preset"] = {
            short_text(path, k, "a 'preset' key"): setting(path, v, f"field 'preset.{k}'")
            for k, v in preset.items()
        }
    if "seed" in info:
        generator["seed"] = values.integer(path, info["seed"], "field 'seed'", 0, 2**63 - 1)
    return generator


def load_meganerf(root: Path, downscale: int) -> SourceScene:
    origin, scale = read_coordinates(root)
    gt = root / "gt"
    with_depth = (gt / "depth").is_dir()
    splits = {
        s: read_split(root, s, origin, scale, downscale, with_depth) for s in ("train", "val")
    }
    if not splits["train"].names:
        raise SceneError(
            root / "train" / "metadata", "the train split is empty: no *.pt metadata files"
        )
    extras = {"origin_drb": origin.tolist(), "pose_scale_factor": scale}
    occupied = aabb = None
    if (gt / "occupancy.npz").is_file():
        occupied, aabb = read_occupancy(scene_file(root, gt / "occupancy.npz"))
    if (gt / "scene.json").is_file():
        extras["generator"] = read_generator(scene_file(root, gt / "scene.json"))
    return SourceScene(
        format="meganerf",
        root=root,
        splits=splits,
        axes=DRB_TO_ZUP.float(),
        units="metres",
        downscale=downscale,
        occupied=occupied,
        occupancy_aabb=aabb,
        extras=extras,
    )

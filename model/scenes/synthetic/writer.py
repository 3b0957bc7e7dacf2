"""Renders the views and writes the scene folder (Mega-NeRF format + gt/) atomically and
byte-for-byte deterministically: a temporary sibling folder renamed into place at the end."""

from __future__ import annotations

import io
import json
import os
import shutil
import time
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from model.scenes.synthetic.flight import flight_poses, intrinsics
from model.scenes.synthetic.geometry import KIND_NAMES, CityGeometry
from model.scenes.synthetic.layouts import build_city
from model.scenes.synthetic.occupancy import occupancy_grid
from model.scenes.synthetic.presets import CityPreset, get_preset
from model.scenes.synthetic.shading import shade

GENERATOR = "leco-synthetic-city"
VERSION = 2  # 2: float64 ray casting with culling, exact boxes and box kinds in scene.json
# (x, y, z) east-north-up -> Mega-NeRF down-right-back: (-z, x, -y).
DRB_FROM_ENU = torch.tensor(
    [[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64
)
FIXED_ZIP_TIME = (2020, 1, 1, 0, 0, 0)


def render_view(geometry: CityGeometry, c2w: torch.Tensor, intr: torch.Tensor, p: CityPreset):
    """uint8 image (H, W, 3) with s x s supersampling, and float32 depth (H, W) of the pixel-centre
    rays."""
    s = p.supersample
    fx, fy, cx, cy = intr.tolist()
    offsets = (torch.arange(s, dtype=torch.float64) + 0.5) / s  # sub-pixel positions
    v, u = torch.meshgrid(
        torch.arange(p.height, dtype=torch.float64),
        torch.arange(p.width, dtype=torch.float64),
        indexing="ij",
    )
    sub_v = (v[..., None, None] + offsets[:, None]).expand(p.height, p.width, s, s)
    sub_u = (u[..., None, None] + offsets[None, :]).expand(p.height, p.width, s, s)
    # Pixel centres go last so the depth comes from exactly the ray the loaders generate.
    pu = torch.cat([sub_u.reshape(-1), u.reshape(-1) + 0.5])
    pv = torch.cat([sub_v.reshape(-1), v.reshape(-1) + 0.5])
    d_cam = torch.stack([(pu - cx) / fx, -(pv - cy) / fy, -torch.ones_like(pu)], dim=-1)
    dirs = d_cam @ c2w[:, :3].T
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    origins = c2w[:, 3].expand_as(dirs)
    colour, t = shade(geometry, origins, dirs)
    n_sub = p.height * p.width * s * s
    linear = colour[:n_sub].reshape(p.height, p.width, s * s, 3).mean(dim=2)
    srgb = linear.clamp(0, 1) ** (1 / 2.2)
    image = torch.round(srgb * 255).to(torch.uint8)
    depth = t[n_sub:].reshape(p.height, p.width).float()
    return image, depth


def loaded_pose(stored: torch.Tensor, origin_drb: torch.Tensor, scale: float) -> torch.Tensor:
    """The float64 generator-frame c2w that a loader rebuilds from a stored (normalised, DRB)
    one."""
    c2w = stored.double()
    c2w[:, 3] = origin_drb + scale * c2w[:, 3]
    return DRB_FROM_ENU.T @ c2w


def save_pt(obj, path: Path) -> None:
    torch.save(obj, path)


def save_png(image: torch.Tensor, path: Path) -> None:
    Image.fromarray(image.numpy()).save(path)


def save_npz(path: Path, **arrays: np.ndarray) -> None:
    """Like np.savez_compressed, but with fixed zip timestamps so the bytes are reproducible."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, array in arrays.items():
            buf = io.BytesIO()
            np.save(buf, array, allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=FIXED_ZIP_TIME)
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, buf.getvalue())


def crop_offsets(preset: CityPreset, seed: int, renders: int) -> np.ndarray:
    """(renders, crops, 2) pixel offsets (x, y) of each view's crop in its render; zeros without a
    margin."""
    out = np.zeros((renders, preset.crops_per_render, 2), dtype=np.int64)
    spare_x = int(round(preset.width * preset.render_margin)) - preset.width
    spare_y = int(round(preset.height * preset.render_margin)) - preset.height
    if spare_x or spare_y:
        rng = np.random.default_rng(seed + 104729)
        out[..., 0] = rng.integers(0, spare_x + 1, out.shape[:2])
        out[..., 1] = rng.integers(0, spare_y + 1, out.shape[:2])
    return out


def write_scene(tmp: Path, preset: CityPreset, seed: int) -> dict:
    geometry = build_city(preset, seed)
    renders = -(-preset.views // preset.crops_per_render)
    poses = flight_poses(replace(preset, views=renders), geometry.extent, seed)
    # Every render is `render_margin` times the image and keeps the images' focal length; a view is
    # a crop of it.
    render_preset = replace(
        preset,
        width=int(round(preset.width * preset.render_margin)),
        height=int(round(preset.height * preset.render_margin)),
    )
    focal = float(intrinsics(preset)[0])
    # float32 values, as the metadata files store them: the rays rendered are the rays a loader
    # makes.
    render_intr = (
        torch.tensor([focal, focal, render_preset.width / 2, render_preset.height / 2])
        .float()
        .double()
    )
    offsets = crop_offsets(preset, seed, renders)
    positions_drb = poses[:, :, 3] @ DRB_FROM_ENU.T
    origin_drb = positions_drb.mean(dim=0)
    scale = float((positions_drb - origin_drb).abs().max())
    save_pt({"origin_drb": origin_drb, "pose_scale_factor": scale}, tmp / "coordinates.pt")

    counts = {"train": 0, "val": 0}
    for r, c2w in enumerate(poses):
        stored = DRB_FROM_ENU @ c2w
        stored[:, 3] = (stored[:, 3] - origin_drb) / scale
        stored = stored.float()
        # Render from the pose as stored (float32) and read back the way a loader does, so the depth
        # maps are exact for the rays a loader makes, even those grazing the horizon or an edge.
        full_image, full_depth = render_view(
            geometry, loaded_pose(stored, origin_drb, scale), render_intr, render_preset
        )
        for k, (dx, dy) in enumerate(offsets[r].tolist()):
            i = r * preset.crops_per_render + k
            if i >= preset.views:
                break
            split = preset.split_of(i)
            counts[split] += 1
            name = f"{i:06d}"
            window = (slice(dy, dy + preset.height), slice(dx, dx + preset.width))
            intr = (render_intr - torch.tensor([0.0, 0.0, dx, dy], dtype=torch.float64)).float()
            for sub in ("rgbs", "metadata"):
                (tmp / split / sub).mkdir(parents=True, exist_ok=True)
            save_png(full_image[window].contiguous(), tmp / split / "rgbs" / f"{name}.png")
            save_pt(
                {"W": preset.width, "H": preset.height, "intrinsics": intr, "c2w": stored},
                tmp / split / "metadata" / f"{name}.pt",
            )
            if preset.depth_maps:
                (tmp / "gt" / "depth" / split).mkdir(parents=True, exist_ok=True)
                np.save(
                    tmp / "gt" / "depth" / split / f"{name}.npy",
                    full_depth[window].contiguous().numpy(),
                )

    occupied, grid_min, cell = occupancy_grid(geometry)
    world_from_grid = torch.eye(4, dtype=torch.float64)
    world_from_grid[:3, :3] = DRB_FROM_ENU * cell
    world_from_grid[:3, 3] = DRB_FROM_ENU @ grid_min
    (tmp / "gt").mkdir(exist_ok=True)
    save_npz(
        tmp / "gt" / "occupancy.npz",
        occupied=occupied.numpy(),
        world_from_grid=world_from_grid.numpy(),
    )
    fraction = float(occupied.float().mean())
    info = {
        "generator": GENERATOR,
        "version": VERSION,
        "preset": preset.as_dict(),
        "seed": seed,
        "units": "metres",
        "frames": {
            "generator": "x east, y north, z up; ground plane z = 0; district centred on the "
            "origin",
            "files": "Mega-NeRF down-right-back: drb = (-z, x, -y); c2w positions normalised by "
            "origin_drb and pose_scale_factor of coordinates.pt",
            "camera": "c2w columns: right, up, back (OpenGL; the camera looks along -back); the "
            "ray through pixel (u, v) has camera direction normalise([(u + 0.5 - cx) / "
            "fx, -(v + 0.5 - cy) / fy, -1])",
            "depth": "gt/depth/<split>/<name>.npy: float32 metres along the unit pixel-centre ray, "
            "inf for sky" + ("" if preset.depth_maps else " (not written for this preset)"),
            "crops": f"each render is {preset.render_margin}x the image size; views are crops of "
            f"it, {preset.crops_per_render} per render, their principal points shifted by "
            "the crop offset",
            "occupancy": "gt/occupancy.npz: occupied[i, j, k] (i east, j north, k up); "
            "world_from_grid maps grid coordinates (cell i spans [i, i+1]) to DRB "
            "metres",
        },
        "occupancy_rule": "a cell is occupied iff it overlaps a solid (box or ground z <= 0) with "
        "positive volume",
        "cell_size": cell,
        "grid_shape": list(occupied.shape),
        "occupied_fraction": round(fraction, 6),
        "counts": {
            "buildings": int(geometry.building.max()),
            "boxes": len(geometry.boxes),
            "views": counts,
        },
        # Full float repr (JSON round-trips it exactly), so the boxes rebuild the geometry bit for
        # bit.
        "boxes": geometry.boxes.tolist(),
        "box_kinds": geometry.kind.tolist(),
        "kind_names": {str(k): v for k, v in KIND_NAMES.items()},
    }
    (tmp / "gt" / "scene.json").write_text(json.dumps(info, indent=1, sort_keys=True))
    return {
        "views": counts,
        "image_size": f"{preset.width}x{preset.height}",
        "occupied_fraction": round(fraction, 6),
        "grid_shape": list(occupied.shape),
        "boxes": len(geometry.boxes),
    }


def generate(preset: str | CityPreset, seed: int, out: str | Path) -> dict:
    """Write a synthetic city to `out` (which must not exist, or be an empty folder). Nothing is
    left behind on failure: the scene appears at `out` complete, or not at all."""
    preset = get_preset(preset)
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise FileExistsError(
            f"{out}: output folder exists and is not empty; choose another --out or remove it"
        )
    started = time.perf_counter()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        summary = write_scene(tmp, preset, seed)
        if out.exists():
            out.rmdir()
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return {
        "path": str(out),
        "preset": preset.name,
        "seed": seed,
        **summary,
        "seconds": round(time.perf_counter() - started, 2),
    }

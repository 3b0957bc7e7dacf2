"""Geometry of a finished run in the dataset's own frame and units: `leco export` and the service's
export jobs. Each export writes its file and `transform.json` beside it, which says how the
normalised world the networks live in maps to that frame (world = (axes @ source - origin) / scale).

- pointcloud.ply: for every `stride`-th pixel of the training and validation views, the point at the
  ray's expected depth (over the foreground's opacity), kept when the ray is at least `min_opacity`
  opaque, coloured by the render (a training view with its own appearance embedding, a validation
  view with the mean);
- cameras.json: every camera (name, split, camera-to-world with OpenGL axes, intrinsics, size);
- occupancy.ply: the centres of the cells of a grid over the foreground box that the method's
  occupancy keeps.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterable, Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from model.scenes.camera_paths import world_to_source_pose
from model.scenes.cameras import Cameras
from model.scenes.scene import Scene, Views
from workers.render.frames import appearance_row, render_frame
from workers.render.schemas import EXPORT_PHASE, ExportConfig
from workers.store import RunStore, check_stop
from workers.trained import Trained

FILES = {"pointcloud": "pointcloud.ply", "cameras": "cameras.json", "occupancy": "occupancy.ply"}
TRANSFORM = "transform.json"


def transform(scene: Scene) -> dict:
    n = scene.normalization
    world_from_source = torch.eye(4, dtype=torch.float64)
    world_from_source[:3, :3] = n.axes.double() / n.scale
    world_from_source[:3, 3] = -n.origin.double() / n.scale
    return {
        "frame": f"the dataset's own ({scene.format}, {scene.root.name})",
        "units": n.units,
        "world_from_source": world_from_source.tolist(),
        "source_from_world": torch.linalg.inv(world_from_source).tolist(),
        "source_units_per_world_unit": n.scale,
        "foreground_box_world": scene.bounds.aabb.tolist(),
        "note": "exported files are in the source frame; the networks and the API's camera routes "
        "use the world",
    }


PLY_XYZ = [
    "property double x",
    "property double y",
    "property double z",
]


def write_ply(path: Path, points: np.ndarray, colours: np.ndarray | None = None) -> None:
    """Binary PLY, float64 positions (source coordinates can be large: UTM metres), optional uint8
    colours."""
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    header = [
        "ply",
        "format binary_little_endian 1.0",
        f"element vertex {len(points)}",
        *PLY_XYZ,
    ]
    if colours is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    data = np.empty(len(points), dtype=np.dtype(fields))
    for k, axis in enumerate("xyz"):
        data[axis] = points[:, k]
    if colours is not None:
        for k, channel in enumerate(("red", "green", "blue")):
            data[channel] = colours[:, k]
    tmp = path.with_suffix(".partial")
    with tmp.open("wb") as f:
        f.write(("\n".join(header) + "\nend_header\n").encode())
        f.write(data.tobytes())
    tmp.replace(path)


def read_ply_points(path: Path) -> np.ndarray:
    """(N, 3) positions of a PLY written by `write_ply`."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:end].decode().splitlines()
    count = int(next(line.split()[2] for line in header if line.startswith("element vertex")))
    fields = [
        (line.split()[2], "<f8" if line.split()[1] == "double" else "u1")
        for line in header
        if line.startswith("property")
    ]
    data = np.frombuffer(raw[end:], dtype=np.dtype(fields), count=count)
    return np.stack([data["x"], data["y"], data["z"]], axis=1)


def stride_cameras(views: Views, stride: int) -> Cameras:
    """The views' cameras over every `stride`-th pixel: the same rays through those pixels'
    centres."""
    cameras = views.cameras
    if stride == 1:
        return cameras
    fx, fy, cx, cy = cameras.intrinsics.unbind(-1)
    # The strided image's pixel u' covers original pixels s u' .. s u' + s - 1; its centre is their
    # centre.
    intrinsics = torch.stack([fx / stride, fy / stride, cx / stride, cy / stride], dim=-1)
    width, height = cameras.width // stride, cameras.height // stride
    return replace(cameras, intrinsics=intrinsics, width=width, height=height)


class Subsample:
    """At most `size` of the points offered, a uniform seeded choice without replacement, in the
    memory of `size` points and one batch: each point draws a random key and the `size` smallest
    keys are kept (a bottom-k sample), merged batch by batch. Points come out in the order they
    were offered."""

    def __init__(self, size: int, seed: int = 0):
        self.size, self.rng = size, np.random.default_rng(seed)
        self.offered = 0
        self.keys = np.zeros(0)
        self.order = np.zeros(0, np.int64)
        self.points = np.zeros((0, 3))
        self.colours = np.zeros((0, 3), np.uint8)

    def offer(self, points: np.ndarray, colours: np.ndarray) -> None:
        keys = self.rng.random(len(points))
        order = np.arange(self.offered, self.offered + len(points))
        self.offered += len(points)
        self.keys = np.concatenate([self.keys, keys])
        self.order = np.concatenate([self.order, order])
        self.points = np.concatenate([self.points, points])
        self.colours = np.concatenate([self.colours, colours])
        if len(self.keys) > self.size:
            keep = np.argpartition(self.keys, self.size - 1)[: self.size]
            self.keys, self.order = self.keys[keep], self.order[keep]
            self.points, self.colours = self.points[keep], self.colours[keep]

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        ordered = np.argsort(self.order, kind="stable")
        return self.points[ordered], self.colours[ordered]


def point_cloud(
    trained: Trained, cfg: ExportConfig, store: RunStore | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(points in the source frame (N, 3) float64, colours (N, 3) uint8): at most
    `cfg.max_points`, kept in that memory however many views and pixels the scene has."""
    scene, kept = trained.scene, Subsample(cfg.max_points)
    mean = appearance_row(trained, "mean")
    views_list = [(name, scene.splits[name]) for name in ("train", "val") if name in scene.splits]
    total, done = sum(len(v) for _, v in views_list), 0
    for split, views in views_list:
        cameras = stride_cameras(views, cfg.stride)
        for i in range(len(views)):
            row = int(views.appearance[i]) if split == "train" else mean
            check_stop(store)
            frame = render_frame(trained, cameras, i, row)
            world, keep = frame.surface_points(cfg.min_opacity)
            kept.offer(
                scene.normalization.to_source(world).numpy(),
                (frame.rgb[keep] * 255).round().clamp(0, 255).byte().numpy(),
            )
            done += 1
            if store is not None:
                store.write(
                    done,
                    {"phase": EXPORT_PHASE, "phase_step": done, "views_done": done, "views": total},
                )
    return kept.result()


def cameras_json(scene: Scene) -> dict:
    cameras = []
    for split, views in scene.splits.items():
        for i, name in enumerate(views.names):
            c = views.cameras
            cameras.append(
                {
                    "name": name,
                    "split": split,
                    "c2w": world_to_source_pose(c.c2w[i], scene.normalization).tolist(),
                    "intrinsics": c.intrinsics[i].tolist(),
                    "width": int(c.width[i]),
                    "height": int(c.height[i]),
                    "distortion": c.distortion[i].tolist(),
                }
            )
    return {
        "frame": "source",
        "units": scene.normalization.units,
        "downscale": scene.downscale,
        "convention": "c2w: OpenGL camera axes (right, up, back) and centre; intrinsics fx, fy, "
        "cx, cy in pixels of the image size given; distortion: OpenCV k1, k2, p1, p2",
        "cameras": cameras,
    }


CHUNK = 1 << 18  # grid cells asked of the occupancy at once


def occupancy_cells(trained: Trained, resolution: int) -> Iterator[np.ndarray]:
    """Centres (source frame, float64) of the grid cells over the foreground box that the method's
    occupancy keeps, a chunk at a time. Centres are made from their flat index (i slowest, as a
    meshgrid "ij" lists them): the whole grid at resolution 512 is 134 million centres."""
    occupied = trained.method.final_occupancy(trained.models)
    if occupied is None:
        raise ValueError(
            f"method {trained.cfg.method!r} learns no occupancy: there is none to export"
        )
    aabb = trained.scene.bounds.aabb.double()
    cells = resolution**3
    with torch.no_grad():
        for start in range(0, cells, CHUNK):
            index = torch.arange(start, min(start + CHUNK, cells))
            ijk = torch.stack(
                [index // resolution**2, (index // resolution) % resolution, index % resolution], -1
            )
            chunk = aabb[0] + (ijk.double() + 0.5) / resolution * (aabb[1] - aabb[0])
            kept = chunk[occupied(chunk.float().to(trained.device)).cpu()]
            yield trained.scene.normalization.to_source(kept).numpy()


def cell_side(trained: Trained, resolution: int) -> float:
    """A grid cell's side in source units."""
    aabb = trained.scene.bounds.aabb.double()
    return float((aabb[1] - aabb[0]).max()) / resolution * trained.scene.normalization.scale


def write_ply_chunks(path: Path, chunks: Iterable[np.ndarray]) -> int:
    """The binary PLY of write_ply (no colours) from points that come a chunk at a time, in the
    memory of one chunk: the vertices go to a file beside it, then the header (which counts them)
    and the vertices into the PLY. Returns the number of points."""
    body, tmp = path.with_suffix(".vertices"), path.with_suffix(".partial")
    count = 0
    try:
        with body.open("wb") as f:
            for points in chunks:
                f.write(np.ascontiguousarray(points, dtype="<f8").tobytes())
                count += len(points)
        header = ["ply", "format binary_little_endian 1.0", f"element vertex {count}", *PLY_XYZ]
        with tmp.open("wb") as out, body.open("rb") as f:
            out.write(("\n".join(header) + "\nend_header\n").encode())
            shutil.copyfileobj(f, out, 1 << 22)
        tmp.replace(path)
    finally:
        body.unlink(missing_ok=True)
        tmp.unlink(missing_ok=True)
    return count


def export(
    trained: Trained, cfg: ExportConfig, out_dir: Path, store: RunStore | None = None
) -> dict:
    """Writes the asked-for file and transform.json into `out_dir`; returns what was written."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / FILES[cfg.what]
    info: dict = {
        "what": cfg.what,
        "file": target.name,
        "transform": TRANSFORM,
        "units": trained.scene.normalization.units,
    }
    if cfg.what == "pointcloud":
        points, colours = point_cloud(trained, cfg, store)
        write_ply(target, points, colours)
        info.update(points=len(points), stride=cfg.stride, min_opacity=cfg.min_opacity)
    elif cfg.what == "cameras":
        tmp = target.with_suffix(".partial")
        tmp.write_text(json.dumps(cameras_json(trained.scene), indent=1))
        tmp.replace(target)
        info.update(cameras=trained.scene.num_images)
    else:
        cells = write_ply_chunks(target, occupancy_cells(trained, cfg.resolution))
        info.update(
            cells=cells, resolution=cfg.resolution, cell_side=cell_side(trained, cfg.resolution)
        )
    (out_dir / TRANSFORM).write_text(json.dumps(transform(trained.scene), indent=1))
    (out_dir / "export.json").write_text(json.dumps(info, indent=1))
    return info

"""A synthetic drone flight as a folder of photos: the synthetic city's exact renders written as
JPEGs with the EXIF a drone writes (focal length, GPS), and truth.json with the exact cameras. It
is what `leco scene poses` is measured on: the poses it finds against the exact ones after a
similarity alignment, and with GPS the scale against true metres.

    python -m bench.photo_flight write --out DIR [--preset city] [--seed 0] [--views 40]
                                       [--size 320x240] [--no-gps] [--no-focal]
    python -m bench.photo_flight compare --truth DIR/truth.json --scene SCENE
    python -m bench.photo_flight compare --published FOLDER --scene SCENE   (e.g. fern's LLFF poses)
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from workers.poses import geodesy
from workers.poses.exif import write_jpeg

ORIGIN = geodesy.Geodetic(47.3769, 8.5417, 408.0)  # where the flight is placed on the globe
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0])


def mapping_poses(extent: float, views: int, altitude: float, pitch_deg: float, seed: int):
    """(views, 3, 4) OpenGL camera-to-world poses of a drone mapping mission: rows across the
    district, every camera facing north (a fixed gimbal heading, as mapping missions fly), rows
    alternating 5 degrees either side of `pitch_deg` below the horizon, the aimed ground points on
    a grid over the middle 80% of the district, with a few metres and degrees of jitter."""
    import torch

    from model.scenes.synthetic.flight import look_pose

    rng = np.random.default_rng(seed + 104_723)
    rows = max(2, int(round(math.sqrt(views / 1.5))))
    per_row = [views // rows + (1 if r < views % rows else 0) for r in range(rows)]
    poses = []
    for r, count in enumerate(per_row):
        # rows alternate between two gimbal pitches, 5 degrees either side: views of one place
        # from two angles pin the focal length down (one pitch leaves it trading with the poses)
        row_pitch = pitch_deg + (5.0 if r % 2 else -5.0)
        ahead = altitude / math.tan(math.radians(row_pitch))  # to its aimed point, on the ground
        north = extent * (-0.4 + 0.8 * (r + 0.5) / rows)
        for k in range(count):
            east = extent * (-0.4 + 0.8 * (k + 0.5) / count)
            yaw = math.pi / 2 + math.radians(rng.uniform(-3.0, 3.0))
            position = np.array(
                [
                    east + rng.uniform(-2, 2),
                    north - ahead + rng.uniform(-2, 2),
                    altitude * rng.uniform(0.97, 1.03),
                ]
            )
            pitch = math.radians(row_pitch + rng.uniform(-3.0, 3.0))
            poses.append(look_pose(position, yaw, pitch))
    return torch.stack(poses)


def write_flight(
    out: Path,
    *,
    preset: str = "city",
    seed: int = 0,
    views: int = 40,
    size: tuple[int, int] = (320, 240),
    gps: bool = True,
    focal: bool = True,
    supersample: int = 3,
    pitch_deg: float = 60.0,
) -> dict:
    """Photos in out/photos (DJI_0000.JPG, ...) and out/truth.json; returns the truth."""
    from model.scenes.synthetic.flight import intrinsics
    from model.scenes.synthetic.layouts import build_city
    from model.scenes.synthetic.presets import get_preset
    from model.scenes.synthetic.writer import render_view

    p = replace(
        get_preset(preset), views=views, width=size[0], height=size[1], supersample=supersample
    )
    geometry = build_city(p, seed)
    poses = mapping_poses(geometry.extent, views, p.altitude, pitch_deg, seed)
    intr = intrinsics(p)
    photos = Path(out) / "photos"
    photos.mkdir(parents=True, exist_ok=False)
    centres = poses[:, :, 3].numpy()
    places = geodesy.from_enu(centres, ORIGIN)
    names = []
    for i, c2w in enumerate(poses):
        image, _ = render_view(geometry, c2w, intr, p)
        name = f"DJI_{i:04d}.JPG"
        write_jpeg(
            photos / name,
            image.numpy(),
            focal_px=float(intr[0]) if focal else None,
            gps=tuple(places[i]) if gps else None,
        )
        names.append(name)
    truth = {
        "frame": "x east, y north, z up (metres) of the origin; c2w columns right, up, back",
        "origin": vars(ORIGIN),
        "preset": preset,
        "seed": seed,
        "size": list(size),
        "intrinsics": intr.tolist(),
        "district_extent_m": geometry.extent,
        "photos": {n: poses[i].tolist() for i, n in enumerate(names)},
    }
    (Path(out) / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
    return truth


def truth_from_scene(path: Path) -> dict:
    """The published cameras of a posed scene (any format `leco scene info` reads) as a truth for
    `pose_errors`: photos by file stem, in the scene's normalised world (a similarity of its own
    frame, which the comparison's alignment absorbs)."""
    from model.scenes import load_scene

    scene = load_scene(Path(path))
    photos = {}
    for views in scene.splits.values():
        for name, c2w in zip(views.names, views.cameras.c2w.double()):
            photos[name] = c2w.tolist()
    return {"frame": f"{scene.format} scene {path}, normalised", "photos": photos}


def _umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale s, rotation R and translation t minimising |s R src + t - dst|^2 (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, d, vt = np.linalg.svd(b.T @ a / len(src))
    flip = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        flip[2, 2] = -1
    rotation = u @ flip @ vt
    scale = float(np.trace(np.diag(d) @ flip) / (a**2).sum(axis=1).mean())
    return scale, rotation, mu_d - scale * rotation @ mu_s


def _angle_deg(rotation: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip((np.trace(rotation) - 1) / 2, -1.0, 1.0)))


def pose_errors(truth: dict, scene: Path) -> dict:
    """The posed cameras of a `leco scene poses` folder against the exact ones: centres after a
    similarity alignment of the centres as a share of the extent (the diagonal of the true centres'
    bounding box), rotations in degrees after the best rotation of the orientations, and the scale
    and rotation of the centres' alignment (1 and 0 when the scene is in east-north-up metres)."""
    import pycolmap

    model = pycolmap.Reconstruction(Path(scene) / "sparse" / "0")
    found, exact, found_rot, exact_rot = [], [], [], []
    by_stem = {Path(model.image(i).name).stem: i for i in model.reg_image_ids()}
    for name, c2w in truth["photos"].items():
        image_id = by_stem.get(Path(name).stem)
        if image_id is None:
            continue
        image = model.image(image_id)
        w2c = image.cam_from_world().matrix()
        found_rot.append(w2c[:, :3].T @ OPENGL_FROM_OPENCV)  # c2w rotation, OpenGL axes
        found.append(image.projection_center())
        c2w = np.array(c2w)
        exact_rot.append(c2w[:, :3])
        exact.append(c2w[:, 3])
    found_c, exact_c = np.array(found), np.array(exact)
    scale, rotation, shift = _umeyama(found_c, exact_c)
    aligned = scale * found_c @ rotation.T + shift
    extent = float(np.linalg.norm(exact_c.max(0) - exact_c.min(0)))
    centre_errors = np.linalg.norm(aligned - exact_c, axis=1) / extent
    # Rotations after the one rotation that best maps the found orientations onto the exact ones
    # (the chordal mean of exact @ found^T): the centres' alignment alone fixes the frame poorly
    # when the centres are nearly coplanar (a forward-facing capture such as fern).
    u, _, vt = np.linalg.svd(sum(e @ f.T for f, e in zip(found_rot, exact_rot)))
    turn_by_views = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    angles = [_angle_deg((turn_by_views @ f).T @ e) for f, e in zip(found_rot, exact_rot)]
    turn = _angle_deg(rotation)
    return {
        "photos": len(truth["photos"]),
        "registered": len(found),
        "extent": extent,  # in the truth's units (metres for a flight)
        "centre_error_share": {
            "median": float(np.median(centre_errors)),
            "max": float(centre_errors.max()),
        },
        "rotation_error_deg": {"median": float(np.median(angles)), "max": float(max(angles))},
        "scale": scale,  # true metres per scene unit
        "frame_rotation_deg": turn,  # 0 when the scene's axes are east, north and up
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.photo_flight", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    write = commands.add_parser("write", help="write a synthetic flight's photos and truth")
    write.add_argument("--out", required=True)
    write.add_argument("--preset", default="city")
    write.add_argument("--seed", type=int, default=0)
    write.add_argument("--views", type=int, default=40)
    write.add_argument("--size", default="320x240", help="WIDTHxHEIGHT")
    write.add_argument("--no-gps", action="store_true")
    write.add_argument("--no-focal", action="store_true")
    compare = commands.add_parser("compare", help="a posed scene against the flight's truth")
    given = compare.add_mutually_exclusive_group(required=True)
    given.add_argument("--truth", help="a flight's truth.json")
    given.add_argument("--published", help="a scene folder whose cameras are the truth")
    compare.add_argument("--scene", required=True)
    args = parser.parse_args(argv)
    if args.command == "write":
        width, height = (int(v) for v in args.size.lower().split("x"))
        write_flight(
            Path(args.out),
            preset=args.preset,
            seed=args.seed,
            views=args.views,
            size=(width, height),
            gps=not args.no_gps,
            focal=not args.no_focal,
        )
        print(Path(args.out) / "photos")
    else:
        truth = (
            json.loads(Path(args.truth).read_text())
            if args.truth
            else truth_from_scene(Path(args.published))
        )
        print(json.dumps(pose_errors(truth, Path(args.scene)), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

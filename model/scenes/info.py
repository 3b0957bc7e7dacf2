"""What `leco scene info` shows: a JSON-able summary of a loaded scene, and its text rendering."""

from __future__ import annotations

from collections import Counter

import torch

from model.scenes.bounds import COVERAGE_RATIO, FAR_FACTOR, MARGIN
from model.scenes.formats.llff import image_folders
from model.scenes.rays import PixelTable
from model.scenes.scene import Scene

BOUNDS_RULE = (
    "foreground box = extent of the evidence points ({source}) within {far}x the median distance "
    "to the nearest camera (and, for surface evidence, in view of at least {coverage}x the median "
    "point's share of cameras), padded {margin:.0%} per side; rays leaving it continue into the "
    "background model"
)


def ray_segment_stats(scene: Scene, max_rays: int = 20_000, seed: int = 0) -> dict:
    """Foreground segments of a seeded sample of training rays (world units)."""
    table = PixelTable(scene.train)
    g = torch.Generator().manual_seed(seed)
    pixels = torch.randint(0, len(table), (min(max_rays, len(table)),), generator=g)
    _, _, _, near, far = table.geometry(pixels, scene.bounds.aabb)  # no pixel is decoded
    hit = far > near
    diagonal = float((scene.bounds.aabb[1] - scene.bounds.aabb[0]).norm())
    stats = {
        "rays_sampled": len(pixels),
        "fraction_hitting_foreground": float(hit.float().mean()),
        # what a march's samples per ray scale with (the memory estimate's ray_fraction)
        "mean_diagonal_fraction": float((far - near).clamp(min=0).mean()) / diagonal,
    }
    near, far = near[hit], far[hit]
    if len(near):
        stats.update(
            near_median=float(near.median()),
            near_min=float(near.min()),
            far_median=float(far.median()),
            far_max=float(far.max()),
        )
    return stats


def describe(scene: Scene) -> dict:
    norm, bounds = scene.normalization, scene.bounds
    # in the z-up, unnormalised frame
    aabb_source = bounds.aabb.double() * norm.scale + norm.origin.double()
    splits = {}
    for name, views in scene.splits.items():
        counts = Counter(
            (int(w), int(h)) for w, h in zip(views.cameras.width, views.cameras.height)
        )
        sizes = sorted(counts)
        splits[name] = {
            "images": len(views),
            "image_sizes": [f"{w}x{h}" for w, h in sizes],
            # images of each size: the API's exact pixel count at any downscale
            # (service/api/feasibility.py)
            "images_by_size": {f"{w}x{h}": counts[(w, h)] for w, h in sizes},
            "focal_px": [
                round(float(views.cameras.intrinsics[:, 0].min()), 3),
                round(float(views.cameras.intrinsics[:, 0].max()), 3),
            ],
            "distorted": bool(views.cameras.distortion.any()),
        }
    occupancy = None
    if scene.occupancy is not None:
        occ = scene.occupancy
        occupancy = {
            "resolution": list(occ.resolution),
            "cell_size_world": [round(float(c), 6) for c in occ.cell_size],
            "occupied_fraction": round(occ.occupied_fraction, 6),
        }
    return {
        "path": str(scene.root),
        "format": scene.format,
        "downscale": scene.downscale,
        # LLFF only: the factors a job's downscale may be a multiple of (images -> 1, images_N -> N)
        **(
            {"image_folder_factors": sorted(image_folders(scene.root))}
            if scene.format == "llff"
            else {}
        ),
        "cameras": scene.num_images,
        "splits": splits,
        "world_convention": "right-handed, z up; camera-to-world in OpenGL axes (right, up, back)",
        "normalisation": {
            "rule": "world = (axes @ source - origin) / scale",
            "axes": [[round(float(x), 6) for x in row] for row in norm.axes],
            "origin": [round(float(x), 6) for x in norm.origin],
            "scale": round(norm.scale, 6),
            "units": norm.units,
        },
        "bounds": {
            "rule": BOUNDS_RULE.format(
                source=bounds.source, far=FAR_FACTOR, coverage=COVERAGE_RATIO, margin=MARGIN
            ),
            "evidence": bounds.source,
            "evidence_points": bounds.num_points,
            "aabb_world": [[round(float(x), 6) for x in row] for row in bounds.aabb],
            "aabb_source": [[round(float(x), 4) for x in row] for row in aabb_source],
            "size_source": [round(float(x), 4) for x in aabb_source[1] - aabb_source[0]],
            "rays": ray_segment_stats(scene),
        },
        "ground_truth": {
            "depth": scene.has_depth,
            "occupancy": occupancy,
        },
        "sparse_points": None if scene.points is None else len(scene.points),
        "extras": scene.extras,
    }


def format_info(info: dict) -> str:
    b, n = info["bounds"], info["normalisation"]
    lines = [
        f"scene      {info['path']}",
        f"format     {info['format']} (downscale {info['downscale']})",
        f"cameras    {info['cameras']}: "
        + ", ".join(
            f"{k} {v['images']} ({'/'.join(v['image_sizes'])})" for k, v in info["splits"].items()
        ),
        f"world      {info['world_convention']}",
        f"normalise  {n['rule']}; origin {n['origin']}, scale {n['scale']} {n['units']} per world "
        "unit",
        f"bounds     from {b['evidence']} ({b['evidence_points']} points)",
        f"  world    min {b['aabb_world'][0]}  max {b['aabb_world'][1]}",
        f"  source   min {b['aabb_source'][0]}  max {b['aabb_source'][1]}  size {b['size_source']} "
        f"{n['units']}",
    ]
    r = b["rays"]
    if "near_median" in r:
        lines.append(
            f"  rays     {r['fraction_hitting_foreground']:.1%} of {r['rays_sampled']} sampled "
            f"train rays cross the box; near median {r['near_median']:.3f}, far median "
            f"{r['far_median']:.3f} (world units)"
        )
    else:
        lines.append(f"  rays     none of {r['rays_sampled']} sampled train rays cross the box")
    gt = info["ground_truth"]
    occ = gt["occupancy"]
    lines.append(
        f"truth      depth maps: {'yes' if gt['depth'] else 'no'}; occupancy: "
        + (
            f"{'x'.join(map(str, occ['resolution']))} grid, {occ['occupied_fraction']:.2%} occupied"
            if occ
            else "no"
        )
    )
    if info["sparse_points"] is not None:
        lines.append(f"points     {info['sparse_points']} sparse points")
    lines.append(f"rule       {b['rule']}")
    return "\n".join(lines)

"""Final evaluation of a finished run (also `leco eval --run RUN_DIR`): PSNR / SSIM / LPIPS (VGG and AlexNet)
on the validation views, the paper's occupancy metrics when the scene has depth maps, validation renders, and an
occupancy point cloud (PLY coloured by predicted colour and alpha, like the paper's Fig. 6/7)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from model.lpips import LPIPSScores
from model.metrics import psnr, ssim
from model.occupancy_eval import evaluate_occupancy, evaluate_occupancy_exact
from model.samplers import stratified_edges
from model.scenes.rays import PixelTable
from workers.appearance import prepare_validation_appearance, protocol, right_columns, scored_truth
from workers.pixels import attach_pixel_stores
from workers.trained import load_run
from workers.validation import render_image, save_triptych

OCCUPANCY_RESOLUTION = 64
MAX_RENDERS = 4  # validation views written as PNG
PLY_RAYS = 4096  # validation rays whose coarse samples make the point cloud


def load_final(run_dir: Path, device: torch.device):
    trained = load_run(run_dir, device)
    scene = trained.scene
    attach_pixel_stores(scene, ("val",) if "val" in scene.splits else ("train",))  # what evaluation reads
    return trained.cfg, scene, trained.method, trained.models


def write_ply(path: Path, points: np.ndarray, rgba: np.ndarray) -> None:
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar alpha\nend_header\n")
    row = np.dtype([("xyz", "<f4", 3), ("rgba", "u1", 4)])
    data = np.empty(len(points), dtype=row)
    data["xyz"], data["rgba"] = points, rgba
    tmp = path.with_suffix(".tmp")
    with tmp.open("wb") as f:
        f.write(header.encode())
        f.write(data.tobytes())
    tmp.replace(path)


@torch.no_grad()
def export_point_cloud(path: Path, models, occupied, views, aabb, device, num_coarse: int) -> int:
    """Coarse samples of a seeded subset of validation rays that the occupancy keeps (all of them for the
    vanilla method), coloured by the main network; alpha = 1 - exp(-sigma * delta)."""
    table = PixelTable(views)
    g = torch.Generator().manual_seed(0)
    ids = torch.randperm(len(table), generator=g)[:PLY_RAYS]
    rays = table.rays(ids, aabb).to(device)
    edges = stratified_edges(rays.near, rays.far, num_coarse, None)
    mids, deltas = 0.5 * (edges[:, 1:] + edges[:, :-1]), edges[:, 1:] - edges[:, :-1]
    points = (rays.origins[:, None] + rays.directions[:, None] * mids[..., None]).reshape(-1, 3)
    keep = (deltas.reshape(-1) > 0)
    if occupied is not None:
        keep &= occupied(points)
    n = num_coarse
    models.eval()
    out = models.field(points[keep], rays.directions.repeat_interleave(n, 0)[keep],
                       rays.image_index.repeat_interleave(n, 0)[keep])
    alpha = -torch.expm1(-out.sigma * deltas.reshape(-1)[keep])
    rgba = torch.cat([out.rgb, alpha[:, None]], -1).clamp(0, 1)
    write_ply(path, points[keep].cpu().numpy().astype(np.float32), (rgba * 255).round().byte().cpu().numpy())
    return int(keep.sum())


def evaluate_run(run_dir: str | Path, device: str | torch.device = "cpu") -> dict:
    run_dir, device = Path(run_dir), torch.device(device)
    cfg, scene, method, models = load_final(run_dir, device)
    views = scene.splits.get("val", scene.train)
    table = PixelTable(views)
    has_val = "val" in scene.splits
    if has_val:  # the validation protocol: embeddings from the left halves, right halves scored
        prepare_validation_appearance(method, models, "main", views, scene.train, list(range(len(views))),
                                      scene.bounds.aabb, device, cfg.val_appearance_steps)
    lpips = LPIPSScores(device=device)  # VGG (what the papers report) and AlexNet; null with the reason if absent
    scores: dict[str, list[float]] = {"psnr": [], "ssim": []}
    for image in range(len(views)):
        scored = right_columns(views, image) if has_val else None
        picture = image < MAX_RENDERS
        rgb, depth = render_image(method, models, "main", table, image, scene.bounds.aabb, device,
                                  None if picture else scored)
        if picture:
            save_triptych(run_dir / "renders" / f"final_{views.names[image]}.png", rgb, views.image(image), depth)
            if scored is not None:
                rgb = rgb[:, scored[0] : scored[1]]
        truth = scored_truth(views, image, scored)
        scores["psnr"].append(psnr(rgb, truth))
        scores["ssim"].append(ssim(rgb, truth))
        lpips.add(rgb, truth)
    val = {"psnr": float(np.mean(scores["psnr"])), "ssim": float(np.mean(scores["ssim"])),
           **lpips.report(), "views": len(views),
           "split": "val" if has_val else "train",
           "protocol": protocol(cfg.val_appearance_steps) if has_val else "whole training views scored (no val split)"}

    occupied = method.final_occupancy(models)
    occupancy: dict[str, Any] = {}
    if occupied is not None and scene.occupancy is not None and views.depth is not None:
        occupancy.update(evaluate_occupancy_exact(occupied, scene.occupancy, views, OCCUPANCY_RESOLUTION))
        occupancy["reference"] = "exact ground truth, on the cells the validation views observe"
    elif occupied is not None and views.depth is not None:
        occupancy.update(evaluate_occupancy(occupied, views, scene.bounds.aabb.float(), OCCUPANCY_RESOLUTION))
        occupancy["reference"] = "depth maps of the validation views"
    points = export_point_cloud(run_dir / "occupancy.ply", models, occupied, views, scene.bounds.aabb, device,
                                method.point_cloud_samples())
    result = {"val": val, "occupancy": occupancy, "point_cloud": {"file": "occupancy.ply", "points": points}}
    (run_dir / "eval.json").write_text(json.dumps(result, indent=1))
    return result

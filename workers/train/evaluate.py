"""Final evaluation of a finished run (also `leco eval --run RUN_DIR`): PSNR / SSIM / LPIPS (VGG and
AlexNet) on the validation views, the paper's occupancy metrics when the scene has depth maps (with
the method's other decision rules scored alike), what reaches the main network on validation rays
counted the same way for every method (`rays`), validation renders, and an occupancy point cloud
(PLY coloured by predicted colour and alpha, like the paper's Fig. 6/7)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor

from model.evaluation.lpips import LPIPSScores
from model.evaluation.metrics import psnr, ssim
from model.evaluation.occupancy import evaluate_occupancy, evaluate_occupancy_exact
from model.methods import Method
from model.methods.base import Networks, Occupied
from model.methods.parts import read_parts
from model.render.accounting import step_accounting, surface_accounting
from model.render.samples import stratified_edges
from model.scenes.rays import PixelTable
from model.scenes.scene import Scene, Views
from workers.appearance import prepare_validation_appearance, protocol, right_columns, scored_truth
from workers.config import TrainConfig
from workers.pixels import attach_pixel_caches
from workers.train.validation import render_image, save_triptych
from workers.trained import load_run

OCCUPANCY_RESOLUTION = 64
MAX_RENDERS = 4  # validation views written as PNG
PLY_RAYS = 4096  # validation rays whose coarse samples make the point cloud
# validation rays the `rays` block counts (a seeded subset: seconds, not minutes)
ACCOUNTING_RAYS = 1 << 14
ACCOUNTING_CHUNK = 4096  # rays per render_main call while counting


def load_final(run_dir: Path, device: torch.device) -> tuple[TrainConfig, Scene, Method, Networks]:
    trained = load_run(run_dir, device)
    scene = trained.scene
    # what evaluation reads
    attach_pixel_caches(scene, ("val",) if "val" in scene.splits else ("train",))
    return trained.cfg, scene, trained.method, trained.models


def write_ply(path: Path, points: np.ndarray, rgba: np.ndarray) -> None:
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\nproperty float "
        "x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar "
        "green\nproperty uchar blue\nproperty uchar alpha\nend_header\n"
    )
    row = np.dtype([("xyz", "<f4", 3), ("rgba", "u1", 4)])
    data = np.empty(len(points), dtype=row)
    data["xyz"], data["rgba"] = points, rgba
    tmp = path.with_suffix(".tmp")
    with tmp.open("wb") as f:
        f.write(header.encode())
        f.write(data.tobytes())
    tmp.replace(path)


@torch.no_grad()
def export_point_cloud(
    path: Path,
    models: Networks,
    occupied: Occupied | None,
    views: Views,
    aabb: Tensor,
    device: torch.device,
    num_coarse: int,
) -> int:
    """Coarse samples of a seeded subset of validation rays that the occupancy keeps (all of them
    for the vanilla method), coloured by the main network; alpha = 1 - exp(-sigma * delta)."""
    table = PixelTable(views)
    g = torch.Generator().manual_seed(0)
    ids = torch.randperm(len(table), generator=g)[:PLY_RAYS]
    rays = table.rays(ids, aabb).to(device)
    edges = stratified_edges(rays.near, rays.far, num_coarse, None)
    mids, deltas = 0.5 * (edges[:, 1:] + edges[:, :-1]), edges[:, 1:] - edges[:, :-1]
    points = (rays.origins[:, None] + rays.directions[:, None] * mids[..., None]).reshape(-1, 3)
    keep = deltas.reshape(-1) > 0
    if occupied is not None:
        keep &= occupied(points)
    n = num_coarse
    models.eval()
    out = models.field(
        points[keep],
        rays.directions.repeat_interleave(n, 0)[keep],
        rays.image_index.repeat_interleave(n, 0)[keep],
    )
    alpha = -torch.expm1(-out.sigma * deltas.reshape(-1)[keep])
    rgba = torch.cat([out.rgb, alpha[:, None]], -1).clamp(0, 1)
    write_ply(
        path,
        points[keep].cpu().numpy().astype(np.float32),
        (rgba * 255).round().byte().cpu().numpy(),
    )
    return int(keep.sum())


def accounting_pixels(
    views: Views, count: int = ACCOUNTING_RAYS, seed: int = 0
) -> tuple[Tensor, str]:
    """The validation pixels the `rays` block counts, in order, and the sentence that says which."""
    total = views.num_pixels
    if total <= count:
        return torch.arange(total), f"all {total:,} pixels of the {len(views)} validation views"
    ids = torch.randperm(total, generator=torch.Generator().manual_seed(seed))[:count].sort().values
    return ids, (
        f"a seeded subset (seed {seed}) of {count:,} of the {total:,} pixels of the {len(views)} "
        "validation views"
    )


class RayTotals:
    """Sums over chunks of rays, so the block's shares are over all its rays (not a mean of chunk
    means)."""

    def __init__(self) -> None:
        self.rays = self.hits = self.reached = self.samples = 0.0
        self.surface = self.kept = 0
        # None once a render's weights did not line up with its samples
        self.opacity: float | None = 0.0

    def add_steps(self, step_figures: Mapping[str, float | Tensor], rays: int, bins: int) -> None:
        figures = read_parts(step_figures)
        hits = figures["hit_ray_fraction"] * rays  # step_accounting's shares back to counts
        self.rays += rays
        self.hits += hits
        self.reached += figures["occupancy_ratio"] * hits * bins
        self.samples += figures["samples_per_hit_ray"] * hits

    def add_surface(self, figures: dict[str, Tensor], opacity_known: bool) -> None:
        surface = figures["surface"]
        self.surface += int(surface.sum())
        self.kept += int(figures["kept"].sum())
        if self.opacity is not None and opacity_known:
            self.opacity += float(figures["opacity"][surface].double().sum())
        else:
            self.opacity = None

    def report(self, bins: int) -> dict[str, Any]:
        if not self.hits:  # no ray crossed the box: nothing to keep or drop
            return {"occupancy_ratio": None, "samples_per_hit_ray": None, "hit_ray_fraction": 0.0}
        return {
            "occupancy_ratio": self.reached / (self.hits * bins),
            "samples_per_hit_ray": self.samples / self.hits,
            "hit_ray_fraction": self.hits / self.rays,
        }


def aligned_weights(weights: Tensor, samples: int) -> Tensor | None:
    """Render weights in the order of MainRender.samples: packed as they are, batched (R, N)
    flattened row by row (pack_edges' order); None when they do not line up (the opacity is then not
    reported, the rest is)."""
    flat = weights.reshape(-1) if weights.dim() == 2 else weights
    return flat if len(flat) == samples else None


@torch.no_grad()
def ray_accounting(
    method: Method,
    models: Networks,
    views: Views,
    aabb: Tensor,
    bins: int,
    device: torch.device,
    depth: Sequence[Tensor] | None,
    depth_source: str,
) -> dict[str, Any]:
    """What reaches the main network on validation rays with the final networks in eval mode
    (deterministic samplers), counted on `bins` coarse bins per hit ray as in training
    (model/render/accounting.py); with depth maps (per view, t along unit rays, inf: no surface),
    also whether the bin holding each ray's visible surface is one of them and the foreground's
    opacity on those rays (a sampler that skips a surface leaves it transparent there).
    `depth_source`: where the depth maps come from, or without them why there are none."""
    ids, selection = accounting_pixels(views)
    table = PixelTable(views)
    flat_depth = torch.cat([d.reshape(-1) for d in depth]) if depth is not None else None
    totals = RayTotals()
    was = models.training
    models.eval()
    try:
        for chunk in ids.split(ACCOUNTING_CHUNK):
            rays = table.rays(chunk, aabb).to(device)
            render = method.render_main(models, rays, None, None)
            if render.samples is None:
                return {
                    "selection": selection,
                    "note": "this method's render does not report its samples",
                }
            totals.add_steps(
                step_accounting(render.samples, rays.near, rays.far, bins), len(rays), bins
            )
            if flat_depth is not None:
                weights = aligned_weights(render.rendered.weights, len(render.samples))
                t = flat_depth[chunk].to(device=device, dtype=rays.near.dtype)
                known = (
                    weights
                    if weights is not None
                    else torch.zeros(len(render.samples), device=device)
                )
                figures = surface_accounting(render.samples, known, rays.near, rays.far, t, bins)
                totals.add_surface(figures, weights is not None)
    finally:
        models.train(was)
    block: dict[str, Any] = {
        "selection": selection,
        "rays": int(totals.rays),
        "bins": bins,
        **totals.report(bins),
    }
    if flat_depth is None:
        block["depth_source"] = None
        block["surface_note"] = depth_source
        return block
    block.update(
        {
            "depth_source": depth_source,
            "surface_rays": totals.surface,
            "surface_bin_kept": totals.kept / totals.surface if totals.surface else None,
            "foreground_opacity": (
                totals.opacity / totals.surface
                if totals.surface and totals.opacity is not None
                else None
            ),
        }
    )
    return block


NO_DEPTH = (
    "the scene has no depth maps: no surface to check "
    "(leco bench takes them from the vanilla model)"
)


def depth_source_of(scene: Scene, views: Views) -> str:
    """What the `rays` block's surfaces come from (synthetic scenes ship exact depth), or why there
    are none."""
    if views.depth is None:
        return NO_DEPTH
    return (
        "exact depth maps" if scene.occupancy is not None else "depth maps of the validation views"
    )


def evaluate_run(run_dir: str | Path, device: str | torch.device = "cpu") -> dict:
    run_dir, device = Path(run_dir), torch.device(device)
    cfg, scene, method, models = load_final(run_dir, device)
    views = scene.splits.get("val", scene.train)
    table = PixelTable(views)
    has_val = "val" in scene.splits
    if has_val:  # the validation protocol: embeddings from the left halves, right halves scored
        prepare_validation_appearance(
            method,
            models,
            "main",
            views,
            scene.train,
            list(range(len(views))),
            scene.bounds.aabb,
            device,
            cfg.val_appearance_steps,
        )
    # VGG (what the papers report) and AlexNet; null with the reason if absent
    lpips = LPIPSScores(device=device)
    scores: dict[str, list[float]] = {"psnr": [], "ssim": []}
    for image in range(len(views)):
        scored = right_columns(views, image) if has_val else None
        picture = image < MAX_RENDERS
        rendered = render_image(
            method,
            models,
            "main",
            table,
            image,
            scene.bounds.aabb,
            device,
            None if picture else scored,
        )
        rgb = rendered.rgb
        if picture:
            save_triptych(
                run_dir / "renders" / f"final_{views.names[image]}.png",
                rendered,
                views.image(image),
            )
            if scored is not None:
                rgb = rgb[:, scored[0] : scored[1]]
        truth = scored_truth(views, image, scored)
        scores["psnr"].append(psnr(rgb, truth))
        scores["ssim"].append(ssim(rgb, truth))
        lpips.add(rgb, truth)
    val = {
        "psnr": float(np.mean(scores["psnr"])),
        "ssim": float(np.mean(scores["ssim"])),
        **lpips.report(),
        "views": len(views),
        "split": "val" if has_val else "train",
        "protocol": protocol(cfg.val_appearance_steps)
        if has_val
        else "whole training views scored (no val split)",
    }

    occupied, rules = method.final_occupancy(models), method.decision_rules(models)
    occupancy: dict[str, Any] = {}
    if occupied is not None and scene.occupancy is not None and views.depth is not None:
        occupancy.update(
            evaluate_occupancy_exact(occupied, scene.occupancy, views, OCCUPANCY_RESOLUTION, rules)
        )
        occupancy["reference"] = "exact ground truth, on the cells the validation views observe"
    elif occupied is not None and views.depth is not None:
        occupancy.update(
            evaluate_occupancy(
                occupied, views, scene.bounds.aabb.float(), OCCUPANCY_RESOLUTION, rules=rules
            )
        )
        occupancy["reference"] = "depth maps of the validation views"
    # LeCO's coarse bins: every method counted on them
    bins = cfg.resolved_profile().guided.coarse_samples
    rays = ray_accounting(
        method,
        models,
        views,
        scene.bounds.aabb,
        bins,
        device,
        views.depth,
        depth_source_of(scene, views),
    )
    points = export_point_cloud(
        run_dir / "occupancy.ply",
        models,
        occupied,
        views,
        scene.bounds.aabb,
        device,
        method.point_cloud_samples(),
    )
    result = {
        "val": val,
        "occupancy": occupancy,
        "rays": rays,
        "point_cloud": {"file": "occupancy.ply", "points": points},
    }
    (run_dir / "eval.json").write_text(json.dumps(result, indent=1))
    return result

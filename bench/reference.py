"""The paper's occupancy protocol for scenes without ground truth (section 4.1): depth maps of the
validation views rendered by the trained vanilla Switch-NeRF become the reference occupancy grid,
and the occupancy of LeCO and of the grid are scored against it (with their other decision rules).
The same depth maps give every method's `rays` block its surfaces: whether the bin of each ray's
surface reaches the main network."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from model.evaluation.occupancy import evaluate_occupancy
from model.scenes.rays import PixelTable
from model.scenes.scene import Scene, Views
from workers.renderer import SURFACE_OPACITY, render_rays
from workers.train.evaluate import load_final, ray_accounting

RESOLUTION = 64


def vanilla_depth_maps(switch_run: Path) -> tuple[list[torch.Tensor], tuple[Scene, Views]]:
    """Per validation view: the vanilla model's surface distance along each unit pixel ray (inf:
    none)."""
    _, scene, method, models = load_final(switch_run, torch.device("cpu"))
    views = scene.splits.get("val", scene.train)
    table, aabb = PixelTable(views), scene.bounds.aabb
    maps = []
    for image in range(len(views)):
        rendered = render_rays(method, models, "main", table.image_rays(image, aabb))
        h, w = int(views.cameras.height[image]), int(views.cameras.width[image])
        maps.append(rendered.surface_distance(SURFACE_OPACITY).reshape(h, w))
    return maps, (scene, views)


def vanilla_source(switch_run: Path) -> str:
    return f"depth of the trained vanilla Switch-NeRF ({Path(switch_run).name})"


def against_vanilla(
    switch_run: Path, occupancy_runs: list[Path], ray_runs: list[Path]
) -> dict[str, dict]:
    """One rendering of the vanilla run's depth maps, then `occupancy`: the occupancy metrics of
    each of `occupancy_runs` against them, and `rays`: the `rays` block (workers/train/evaluate.py)
    of each of `ray_runs` (every method, vanilla included) with its surfaces from them; both keyed
    by run folder."""
    maps, (scene, views) = vanilla_depth_maps(switch_run)
    results: dict[str, dict] = {"occupancy": {}, "rays": {}}
    for run_dir in occupancy_runs:
        _, _, method, models = load_final(run_dir, torch.device("cpu"))
        occupied = method.final_occupancy(models)
        metrics: dict[str, Any] = dict(
            evaluate_occupancy(
                occupied,
                views,
                scene.bounds.aabb.float(),
                RESOLUTION,
                depth=maps,
                rules=method.decision_rules(models),
            )
        )
        metrics["reference"] = vanilla_source(switch_run)
        results["occupancy"][str(run_dir)] = metrics
    for run_dir in ray_runs:
        cfg, run_scene, method, models = load_final(run_dir, torch.device("cpu"))
        run_views = run_scene.splits.get("val", run_scene.train)
        results["rays"][str(run_dir)] = ray_accounting(
            method,
            models,
            run_views,
            run_scene.bounds.aabb,
            cfg.resolved_profile().guided.coarse_samples,
            torch.device("cpu"),
            maps,
            vanilla_source(switch_run),
        )
    return results

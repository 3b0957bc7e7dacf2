"""A finished run's networks, ready to render: what evaluation, `leco render` / `leco export` and
the service's render, export and view workers all load. A run folder written by `leco train` knows
its scene (run.json); the service knows it from the database and hands over the stored `final/`
files."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch

from model.methods import Method
from model.methods.base import Networks, method_state
from model.scenes import load_scene
from model.scenes.scene import Scene
from workers.config import TrainConfig
from workers.models import build_models


@dataclass
class Trained:
    cfg: TrainConfig
    scene: Scene
    method: Method
    models: Networks
    device: torch.device
    # the appended mean appearance row, once a render asked for it (workers/render/frames.py)
    mean_row: int | None = None


def load_trained(
    final: Path, scene_path: str | Path, device: torch.device | str = "cpu"
) -> Trained:
    """From a `final/` folder (models.pt and the method's own files) and the scene it was trained
    on."""
    final, device = Path(final), torch.device(device)
    if not (final / "models.pt").is_file():
        raise FileNotFoundError(
            f"{final.parent}: no finished run here (final/models.pt is missing)"
        )
    saved = torch.load(final / "models.pt", map_location=device, weights_only=False)
    cfg = TrainConfig.model_validate(saved["config"])
    # the settings it trained with, not today's defaults for its profile
    profile = saved.get("resolved_profile") or summary_profile(final.parent)
    if profile is not None:
        cfg = cfg.pinned(profile)
    scene = load_scene(scene_path, downscale=cfg.downscale)
    method = cfg.method_for_run()
    models = build_models(method, scene.num_images, scene.bounds.aabb, cfg.seed).to(device)
    method.to(device)
    models.load_state_dict(saved["models"])
    method.load_state_dict(method_state(saved))
    method.load_final(models, final, device)
    models.eval()
    return Trained(cfg, scene, method, models, device)


def summary_profile(run_dir: Path) -> dict | None:
    """A run's resolved profile from its summary.json: what runs saved before models.pt held it."""
    summary = run_dir / "summary.json"
    if not summary.is_file():
        return None
    return json.loads(summary.read_text()).get("resolved_profile")


def load_run(run_dir: str | Path, device: torch.device | str = "cpu") -> Trained:
    """A run folder of `leco train` (its run.json names the scene)."""
    run_dir = Path(run_dir)
    if not (run_dir / "final" / "models.pt").is_file():
        raise FileNotFoundError(f"{run_dir}: no finished run here (final/models.pt is missing)")
    if not (run_dir / "run.json").is_file():
        raise FileNotFoundError(f"{run_dir}: not a run folder (run.json is missing)")
    scene = json.loads((run_dir / "run.json").read_text())["scene"]
    return load_trained(run_dir / "final", scene, device)

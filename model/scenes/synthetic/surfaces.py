"""Distances to the synthetic city's true surfaces (its boxes and the ground plane z = 0), for
checking exported geometry in metres. Points come in the scene's source frame (Mega-NeRF's
down-right-back metres, as `leco export` writes them)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from model.scenes.synthetic.writer import DRB_FROM_ENU


def truth(scene_root: str | Path) -> tuple[np.ndarray, float]:
    """(boxes (K, 2, 3) in ENU metres, ground-truth cell size in metres) from gt/scene.json."""
    info = json.loads((Path(scene_root) / "gt" / "scene.json").read_text())
    return np.asarray(info["boxes"], dtype=np.float64), float(info["cell_size"])


def distance_to_surfaces(
    points_drb: np.ndarray, boxes: np.ndarray, chunk: int = 4096
) -> np.ndarray:
    """Per point, metres to the nearest surface: a box's faces (from outside or inside) or the
    ground."""
    enu = points_drb @ DRB_FROM_ENU.numpy()  # drb = M enu, so enu = M^T drb: rows times M
    best = np.abs(enu[:, 2])
    lo, hi = boxes[:, 0], boxes[:, 1]
    for s in range(0, len(enu), chunk):
        p = enu[s : s + chunk, None, :]
        outside = np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0), axis=-1)
        inside = np.minimum(p - lo, hi - p).min(axis=-1)  # positive only when inside on every axis
        d = np.where(outside > 0, outside, np.maximum(inside, 0.0))
        best[s : s + chunk] = np.minimum(best[s : s + chunk], d.min(axis=1))
    return best

"""Drone cameras along a lawnmower flight grid over the district, looking down obliquely (like
Mill-19)."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from model.scenes.synthetic.presets import CityPreset


def look_pose(position: np.ndarray, yaw: float, pitch: float) -> Tensor:
    """OpenGL camera-to-world (z-up world): columns right, up, back, position."""
    forward = np.array(
        [math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), -math.sin(pitch)]
    )
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return torch.tensor(np.stack([right, up, -forward, position], axis=1), dtype=torch.float64)


def flight_poses(p: CityPreset, extent: float, seed: int) -> Tensor:
    """(views, 3, 4) poses: a main pass along x with alternating headings, then a flatter cross pass
    along y that sees the horizon, each camera aimed so its image centre sweeps the district."""
    rng = np.random.default_rng(seed + 7919)
    half = extent / 2
    main = int(round(p.views * 0.7))
    passes = [(0, main, p.pitch_deg), (1, p.views - main, p.pitch_deg * p.cross_pitch_share)]
    poses = []
    for axis, count, pitch_deg in passes:
        # ground distance to the image centre
        ahead = p.altitude / math.tan(math.radians(pitch_deg))
        lines = max(2, int(round(math.sqrt(count / 2))))
        per_line = [count // lines + (1 if i < count % lines else 0) for i in range(lines)]
        for line, n in enumerate(per_line):
            across = -half * 0.8 + 1.6 * half * (line + 0.5) / lines
            sign = 1.0 if line % 2 == 0 else -1.0
            for k in range(n):
                target_along = sign * (-half * 0.8 + 1.6 * half * (k + 0.5) / n)
                yaw = (
                    (0.0 if sign > 0 else math.pi)
                    + (math.pi / 2 if axis else 0.0)
                    + rng.uniform(-0.15, 0.15)
                )
                target = (
                    np.array([target_along, across])
                    if axis == 0
                    else np.array([across, target_along])
                )
                position = np.array(
                    [
                        *(target - ahead * np.array([math.cos(yaw), math.sin(yaw)])),
                        p.altitude * rng.uniform(0.95, 1.05),
                    ]
                )
                poses.append(
                    look_pose(position, yaw, math.radians(pitch_deg + rng.uniform(-5.0, 5.0)))
                )
    return torch.stack(poses)


def intrinsics(p: CityPreset) -> Tensor:
    focal = 0.5 * p.width / math.tan(math.radians(p.hfov_deg) / 2)
    return torch.tensor([focal, focal, p.width / 2, p.height / 2], dtype=torch.float64)

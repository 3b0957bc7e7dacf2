"""What an estimator is: the part of a method that decides where along a ray the main network
samples, in the spirit of nerfacc's estimators. Every estimator answers one question, whether a
world point may hold a surface (`occupied`); the training scores that answer against the scene's
occupancy (the paper's Table 1), the point-cloud export filters with it, and `sample` marches a
ray through it. How an estimator learns (the grid's update, O's phase 1 and online learning, the
proposals' interlevel loss) is its method's business (model/methods/)."""

from __future__ import annotations

import math
from abc import ABC, abstractmethod

import torch
from torch import Tensor

from model.render.noise import Noise
from model.render.samples import PackedSamples


class Estimator(ABC):
    @abstractmethod
    def occupied(self, points: Tensor) -> Tensor:
        """World points (N, 3) on any device -> bool (N,) on the estimator's own device."""

    @torch.no_grad()
    def sample(
        self,
        origins: Tensor,
        directions: Tensor,
        near: Tensor,
        far: Tensor,
        step_size: float,
        noise: Noise | None = None,
        max_length: float | None = None,
    ) -> PackedSamples:
        """March each ray's foreground segment with a fixed step (jittered by one random offset per
        ray with noise) and keep the intervals whose mid-points are occupied (packed, grouped
        by ray): nerfacc's `sampling` for an occupancy estimator. `max_length`: a bound on every
        segment's length the caller knows (a box's diagonal), so the march's width is set without
        reading the rays (a wait on CUDA); the steps past a ray's far end are dropped, so the
        samples are the same."""
        if max_length is not None:
            steps = max(1, math.ceil(max_length / step_size) + 1)  # +1: the bound's rounding
        else:
            steps = int(torch.ceil(((far - near).max() / step_size)).clamp(min=1))
        offset = (
            noise.rand(len(near), 1, device=near.device) * step_size if noise is not None else 0.0
        )
        starts = (
            near[:, None]
            + offset
            + step_size * torch.arange(steps, dtype=near.dtype, device=near.device)
        )
        ends = torch.minimum(starts + step_size, far[:, None])
        valid = ends > starts
        mids = 0.5 * (starts + ends)
        points = origins[:, None, :] + directions[:, None, :] * mids[..., None]
        keep = valid & self.occupied(points.reshape(-1, 3)).reshape(valid.shape)
        ray, k = torch.nonzero(keep, as_tuple=True)
        return PackedSamples(starts[ray, k], ends[ray, k], ray)

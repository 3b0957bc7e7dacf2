"""S+Grid: nerfacc's occupancy grid (model/estimators/grid.py) marched through by the main network,
updated from the main network's own density as it trains."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor

from model.estimators.grid import GridEstimator
from model.methods.base import Method, Networks, Occupied, Step, SweepPoint, mean_of
from model.methods.main_phase import MainRender, grid_step_size, render_grid
from model.methods.spec import setting
from model.methods.stages import stage
from model.profiles import GridConfig
from model.render.noise import Noise
from model.render.volume import Rendered
from model.scenes.rays import RayBatch


class GridMethod(Method):
    grid: GridEstimator  # made by build()
    grid_section = "grid"  # the profile section of this method's grid

    @property
    def grid_config(self) -> GridConfig:
        return setting(self.profile, self.grid_section)

    def build(self, num_images: int, aabb: Tensor) -> Networks:
        g = self.grid_config
        self.grid = GridEstimator(aabb.float(), g.resolution, g.levels)
        return super().build(num_images, aabb)

    def components(self, num_images: int) -> dict[str, int]:
        g = self.grid_config
        return {**super().components(num_images), "grid_cells": g.levels * g.resolution**3}

    def sweep(self) -> list[SweepPoint]:
        n = self.grid_config.march_steps
        return [
            SweepPoint(tag, f"{m} march steps", {f"{self.grid_section}.march_steps": m})
            for tag, m in (("lean", max(n // 2, 8)), ("rich", 2 * n))
        ]

    def to(self, device: torch.device) -> "GridMethod":
        self.grid.to(device)
        return self

    def step(self, models: Networks, step: Step) -> tuple[Tensor, dict]:
        g, field = self.grid_config, models.field
        was_training = field.training
        field.eval()
        # Same generator on every rank, so the replicated grids stay identical.
        with stage("sampler"):
            self.grid.update(
                step.phase_step,
                lambda x: self.density(models, x),
                grid_step_size(self.grid, g.march_steps),
                g.threshold,
                g.decay,
                g.warmup_steps,
                g.update_every,
                torch.Generator().manual_seed(step.seed * 100_003 + step.phase_step),
            )
        field.train(was_training)
        return super().step(models, step)

    def density(self, models: Networks, x: Tensor) -> Tensor:
        """What the grid's update reads: the field's density in the box and, where cascades reach
        beyond it, the background's."""
        zeros = lambda x: torch.zeros(len(x), dtype=torch.long, device=x.device)
        if self.grid.levels == 1:  # every update point is in the box
            return models.field(x, torch.zeros_like(x), zeros(x)).sigma
        lo, hi = self.grid.aabb
        box = ((x >= lo) & (x < hi)).all(-1)
        sigma = x.new_zeros(len(x))
        if box.any():
            y = x[box]
            sigma[box] = models.field(y, torch.zeros_like(y), zeros(y)).sigma.float()
        if (~box).any():
            y = x[~box]
            sigma[~box] = models.background(y, torch.zeros_like(y), zeros(y))[0].float()
        return sigma

    def render_main(
        self,
        models: Networks,
        rays: RayBatch,
        noise: Noise | None,
        phase_step: int | None,
    ) -> MainRender:
        return self.march(models, rays, noise)

    def render(self, models: Networks, phase: str, rays: RayBatch) -> Rendered:
        """Images march each ray only until it is opaque, as Instant-NGP's renders do."""
        return self.march(models, rays, None, self.grid_config.early_stop_eps).rendered

    def march(
        self,
        models: Networks,
        rays: RayBatch,
        noise: Noise | None,
        early_stop_eps: float = 0.0,
    ) -> MainRender:
        return render_grid(
            models.field,
            models.background,
            rays,
            self.profile.background.samples,
            self.grid_config.march_steps,
            self.grid,
            noise,
            early_stop_eps,
        )

    def occupancy(self, models: Networks, phase: str) -> Occupied | None:
        return self.grid.occupied

    def final_occupancy(self, models: Networks) -> Occupied | None:
        return self.grid.occupied

    def state_dict(self) -> dict | None:
        return {
            "values": self.grid.values,
            "binary": self.grid.binary,
            "queries": self.grid.queries,
        }

    def load_state_dict(self, state: dict | None) -> None:
        if state is not None:
            device = self.grid.values.device
            self.grid.values, self.grid.binary = (
                state["values"].to(device),
                state["binary"].to(device),
            )
            self.grid.queries = state["queries"]

    def summary_occupancy(self, final: Path, main: list[dict], first: list[dict]) -> dict:
        return {
            # one value per cell
            "params": self.grid_config.levels * self.grid_config.resolution**3,
            "occupancy_ratio": mean_of(main, "occupancy_ratio"),
        }

"""The networks, optimizers and schedules of a run, built from the resolved profile. Every rank builds them
from the same seed, so data-parallel replicas start identical."""

from __future__ import annotations

import torch
from torch import nn

from model.model_info import background as build_background, hmoe as build_hmoe, switch_nerf as build_switch
from model.occupancy_grid import OccupancyGrid
from model.profiles import Profile


class RunModels(nn.Module):
    """All trainable state of a run: the HMoE (leco), the main Switch-NeRF, the backgrounds, and the grid."""

    def __init__(self, method: str, profile: Profile, num_images: int, aabb: torch.Tensor, seed: int):
        super().__init__()
        torch.manual_seed(seed)
        if method == "leco":
            self.hmoe = build_hmoe(profile, num_images)
            self.occupancy_background = build_background(profile, num_images)
        self.field = build_switch(profile, num_images)
        self.background = build_background(profile, num_images)
        self.grid = OccupancyGrid(aabb.float(), profile.grid.resolution) if method == "grid" else None

    def to(self, device):
        super().to(device)
        if self.grid is not None:
            self.grid.to(device)
        return self

    def phase_modules(self, phase: str) -> list[nn.Module]:
        return [self.hmoe, self.occupancy_background] if phase == "occupancy" else [self.field, self.background]

    def grid_state(self) -> dict | None:
        if self.grid is None:
            return None
        return {"values": self.grid.values, "binary": self.grid.binary, "queries": self.grid.queries}

    def load_grid_state(self, state: dict | None) -> None:
        if self.grid is not None and state is not None:
            self.grid.values, self.grid.binary, self.grid.queries = state["values"], state["binary"], state["queries"]


def build_optimizer(models: RunModels, phase: str, profile: Profile):
    """Phase 1: Adam at the occupancy lr (constant, as in the paper). Main phase: Adam decaying exponentially
    from lr to lr_final over main_steps (Switch-NeRF)."""
    params = [p for m in models.phase_modules(phase) for p in m.parameters()]
    if phase == "occupancy":
        optimizer = torch.optim.Adam(params, lr=profile.occupancy.lr)
        return params, optimizer, torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: 1.0)
    optimizer = torch.optim.Adam(params, lr=profile.lr)
    gamma = (profile.lr_final / profile.lr) ** (1.0 / profile.main_steps)
    return params, optimizer, torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma)

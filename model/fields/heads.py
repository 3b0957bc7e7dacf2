"""Prediction heads: the shared scene head (density + view- and appearance-dependent colour) and the
empty-space head, which sees nothing but its expert's output."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def density_activation(raw: Tensor, noise_std: float, training: bool) -> Tensor:
    """softplus(x - 1), with N(0, noise_std) noise on the raw value while training (Switch-NeRF)."""
    if training and noise_std > 0:
        raw = raw + torch.randn_like(raw) * noise_std
    return F.softplus(raw - 1.0)


class SceneHead(nn.Module):
    """H_s: sigma = Linear(W, 1); colour = Linear(W, W) -> [dir, appearance] -> Linear -> ReLU ->
    Linear -> sigmoid."""

    def __init__(self, width: int, dir_dim: int, appearance_dim: int, noise_std: float = 1.0):
        super().__init__()
        self.sigma = nn.Linear(width, 1)
        self.feature = nn.Linear(width, width)
        self.colour = nn.Sequential(
            nn.Linear(width + dir_dim + appearance_dim, width // 2),
            nn.ReLU(),
            nn.Linear(width // 2, 3),
        )
        self.noise_std = noise_std

    def forward(
        self, h: Tensor, dir_enc: Tensor, appearance: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """(raw sigma, sigma, rgb)."""
        raw = self.sigma(h).squeeze(-1)
        sigma = density_activation(raw, self.noise_std, self.training)
        rgb = torch.sigmoid(self.colour(torch.cat([self.feature(h), dir_enc, appearance], dim=-1)))
        return raw, sigma, rgb


class EmptyHead(nn.Module):
    """H_e: density and colour from the empty expert's output alone (no direction, no
    appearance)."""

    def __init__(self, width: int, noise_std: float = 1.0):
        super().__init__()
        self.sigma = nn.Linear(width, 1)
        self.colour = nn.Linear(width, 3)
        self.noise_std = noise_std

    def forward(self, h: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        raw = self.sigma(h).squeeze(-1)
        return (
            raw,
            density_activation(raw, self.noise_std, self.training),
            torch.sigmoid(self.colour(h)),
        )

"""Frequency (positional) encoding as in Switch-NeRF: the raw input plus sin/cos at 2^0 .. 2^(n-1),
no pi."""

from __future__ import annotations

import torch
from torch import Tensor, nn


class FrequencyEncoding(nn.Module):
    freqs: Tensor  # a buffer, registered below

    def __init__(self, num_frequencies: int, in_dim: int = 3):
        super().__init__()
        self.in_dim = in_dim
        self.register_buffer(
            "freqs", 2.0 ** torch.arange(num_frequencies, dtype=torch.float32), persistent=False
        )

    @property
    def out_dim(self) -> int:
        return self.in_dim * (1 + 2 * len(self.freqs))

    def forward(self, x: Tensor) -> Tensor:
        scaled = (x[..., None, :] * self.freqs[:, None]).flatten(-2)  # (..., F * in_dim)
        return torch.cat([x, torch.sin(scaled), torch.cos(scaled)], dim=-1)

"""A proposal network (mip-NeRF 360, nerfacto): a small density-only MLP whose histogram along a ray
tells the next level where to put its samples. Positional encoding as in our fields, ReLU layers,
and the same density activation as the main network's (softplus(x - 1))."""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn

from model.fields.encoding import FrequencyEncoding


class ProposalDensity(nn.Module):
    def __init__(self, width: int, layers: int, xyz_frequencies: int):
        super().__init__()
        self.encoding = FrequencyEncoding(xyz_frequencies)
        dims = [self.encoding.out_dim] + [width] * layers
        body: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:]):
            body += [nn.Linear(a, b), nn.ReLU()]
        self.mlp = nn.Sequential(*body, nn.Linear(dims[-1], 1))

    def forward(self, xyz: Tensor) -> Tensor:
        """(N,) density >= 0 at world points (N, 3)."""
        return F.softplus(self.mlp(self.encoding(xyz)).squeeze(-1) - 1.0)

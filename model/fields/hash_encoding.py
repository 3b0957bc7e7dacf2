"""Instant-NGP's multi-resolution hash encoding (Müller et al. 2022, section 3) in plain PyTorch, so
it runs wherever the rest does; autograd scatters the gradients into the tables.

Level l has N_l = floor(N_min * b^l) cells per side, b = exp((ln N_max - ln N_min) / (L - 1)). A
point in [0, 1]^3 falls in one cell of each level; the F features stored at the cell's 8 corners
are blended trilinearly. A level whose (N_l + 1)^3 corners fit in the table of T entries stores
each corner in its own entry (no collision); a finer level hashes corner (i, j, k) to
(i * 1 xor j * 2654435761 xor k * 805459861) mod T, the paper's Eq. 4. The output concatenates the
levels, L * F values per point."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from model.sizes import level_resolutions, level_sizes

PRIMES = (1, 2654435761, 805459861)
# the 8 corners of a cell, as offsets (x, y, z) from its lowest corner
CORNERS = torch.tensor([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)])


class HashEncoding(nn.Module):
    offsets: Tensor  # buffers, registered below
    resolutions_t: Tensor
    hashed: Tensor
    sizes_t: Tensor
    corners: Tensor
    corner_is_high: Tensor

    def __init__(
        self,
        levels: int = 16,
        features: int = 2,
        log2_table_size: int = 19,
        min_resolution: int = 16,
        max_resolution: int = 2048,
    ):
        super().__init__()
        self.levels, self.features = levels, features
        self.table_size = 2**log2_table_size
        self.resolutions = level_resolutions(levels, min_resolution, max_resolution)
        sizes = level_sizes(self.resolutions, self.table_size)
        # one flat table, each level's entries after the previous level's (tiny-cuda-nn's layout)
        offsets = [0]
        for size in sizes:
            offsets.append(offsets[-1] + size)
        # U(-1e-4, 1e-4), the paper's initialisation: near zero, not exactly (symmetry)
        self.table = nn.Parameter(torch.empty(offsets[-1], features).uniform_(-1e-4, 1e-4))
        self.register_buffer("offsets", torch.tensor(offsets[:-1]), persistent=False)
        self.register_buffer("resolutions_t", torch.tensor(self.resolutions), persistent=False)
        self.register_buffer("sizes_t", torch.tensor(sizes), persistent=False)
        hashed = [(n + 1) ** 3 > self.table_size for n in self.resolutions]
        self.register_buffer("hashed", torch.tensor(hashed), persistent=False)
        # on the module's device, so no call copies them there (a copy from the host waits)
        self.register_buffer("corners", CORNERS.clone(), persistent=False)
        self.register_buffer("corner_is_high", CORNERS.bool(), persistent=False)

    @property
    def out_dim(self) -> int:
        return self.levels * self.features

    def corner_indices(self, corners: Tensor) -> Tensor:
        """Rows of the flat table for integer corners (P, L, 8, 3) of each level."""
        n = self.resolutions_t.view(1, -1, 1)
        dense = corners[..., 0] + corners[..., 1] * (n + 1) + corners[..., 2] * (n + 1) ** 2
        hashed = (
            (corners[..., 0] * PRIMES[0])
            ^ (corners[..., 1] * PRIMES[1])
            ^ (corners[..., 2] * PRIMES[2])
        ) & (self.table_size - 1)
        local = torch.where(self.hashed.view(1, -1, 1), hashed, dense)
        return local + self.offsets.view(1, -1, 1)

    def forward(self, x: Tensor) -> Tensor:
        """Features (..., L * F) of points x (..., 3) in [0, 1]^3 (clamped to it)."""
        shape = x.shape[:-1]
        x = x.reshape(-1, 3).clamp(0.0, 1.0)
        scaled = x[:, None, :] * self.resolutions_t.view(1, -1, 1).to(x.dtype)  # (P, L, 3)
        # the cell's lowest corner, kept inside the grid so a point at 1 uses the last cell
        low = scaled.floor().clamp(max=self.resolutions_t.view(1, -1, 1) - 1).long()
        frac = scaled - low  # (P, L, 3) in [0, 1]
        corners = low[:, :, None, :] + self.corners  # (P, L, 8, 3)
        rows = self.corner_indices(corners)  # (P, L, 8)
        # trilinear weight of each corner
        high = self.corner_is_high
        weights = torch.where(high, frac[:, :, None, :], 1 - frac[:, :, None, :]).prod(-1)
        values = self.table[rows]  # (P, L, 8, F)
        blended = (weights[..., None] * values).sum(2)  # (P, L, F)
        return blended.reshape(*shape, self.out_dim)

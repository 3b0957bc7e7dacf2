"""mip-NeRF 360's scene contraction (Barron et al. 2022, Eq. 10): space inside the unit ball stays,
the rest is squeezed into the shell between radius 1 and 2, so an unbounded background fits a
bounded grid. `order=inf` uses the max norm instead (nerfstudio's choice for grids: the contracted
space is then the cube [-2, 2]^3, which a grid covers without waste)."""

from __future__ import annotations

import torch
from torch import Tensor


def contract(x: Tensor, order: float = 2.0) -> Tensor:
    """contract(x) = x if ||x|| <= 1 else (2 - 1 / ||x||) x / ||x||; (..., 3) -> (..., 3), every
    norm below 2."""
    norm = torch.linalg.vector_norm(x, ord=order, dim=-1, keepdim=True)
    # the clamp keeps the unused branch finite at the origin (NaN would reach the gradient)
    safe = norm.clamp(min=1.0)
    return torch.where(norm <= 1.0, x, (2.0 - 1.0 / safe) * (x / safe))


def contracted_unit(x: Tensor, order: float = 2.0) -> Tensor:
    """The contracted point mapped to [0, 1]^3 (a hash grid's input): contract(x) / 4 + 1/2."""
    return contract(x, order) / 4.0 + 0.5

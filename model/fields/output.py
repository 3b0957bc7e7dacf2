"""What a field returns for a batch of points."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor


@dataclass
class FieldOutput:
    sigma: Tensor  # (N,) density >= 0
    rgb: Tensor  # (N, 3) in [0, 1]
    gate_probs: Tensor  # (N, E) fp32 softmax of the gate
    expert: Tensor  # (N,) top-1 expert index (for HMoE the last index is the empty expert)
    kept: Tensor  # (N,) bool: False where a capacity limit dropped the point

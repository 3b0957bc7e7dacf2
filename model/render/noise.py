"""A training step's random draws (jittered intervals, stratified offsets, a march's start).

Training draws from the default generator of the device the tensors are made on; the training
loop lends that generator the run's own state for the step and takes it back after
(workers/train/lent_generator.py), so a step draws what the run's generator would draw, to the
digit, and a checkpoint's generator state resumes it. Code that a step runs never holds a
`torch.Generator`: torch.compile breaks its graph at a draw given one (in any frame but the
first), and a CUDA graph captures only the default generator's draws. A test that wants its own
stream passes `Noise(generator)`.
"""

from __future__ import annotations

import torch
from torch import Tensor


class Noise:
    """Uniform draws in [0, 1); `generator` None: the device's default generator."""

    def __init__(self, generator: torch.Generator | None = None):
        self.generator = generator

    def rand(
        self, *size: int, device: torch.device | None = None, dtype: torch.dtype | None = None
    ) -> Tensor:
        if self.generator is None:
            return torch.rand(*size, device=device, dtype=dtype)
        return torch.rand(*size, generator=self.generator, device=device, dtype=dtype)

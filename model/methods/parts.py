"""A step's loss parts: the figures the log shows of one training step (losses, PSNR, samples per
ray, a sampler's shares).

A method returns each part as a Python number or a detached 0-dim tensor. Reading a tensor makes the
host wait for the device, so parts stay tensors through the step and the training loop reads them
all in one go (`read_parts`) on the steps it logs, never on the others."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import Tensor

from model.methods.stages import host_read

Parts = dict[str, float | Tensor]


def psnr(mse: Tensor) -> Tensor:
    """The PSNR of a mean squared error of colours in [0, 1], floored at 1e-10 (100 dB)."""
    return -10.0 * torch.log10(mse.detach().clamp(min=1e-10))


def read_parts(parts: Mapping[str, float | Tensor]) -> dict[str, float]:
    """Every part as a float: the tensors stacked and read with one host sync. A tensor is read in
    double precision, so a float32 part reads as `float(tensor)` would."""
    names = [k for k, v in parts.items() if isinstance(v, Tensor)]
    read = {k: v for k, v in parts.items() if not isinstance(v, Tensor)}
    if names:
        stacked = torch.stack([_scalar(parts[k]) for k in names])
        read.update(zip(names, host_read(stacked)))
    return {k: read[k] for k in parts}


def _scalar(value: float | Tensor) -> Tensor:
    assert isinstance(value, Tensor)
    if value.numel() != 1:
        raise ValueError(
            f"a loss part must be one number, not a tensor of shape {tuple(value.shape)}"
        )
    return value.detach().reshape(()).double()

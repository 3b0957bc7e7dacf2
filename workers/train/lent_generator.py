"""The run's generator lent to the device's default generator for a step's draws.

A step draws from the default generator (model/render/noise.py says why: torch.compile and CUDA
graphs take no generator object); the run keeps its own, per rank, in its checkpoints. For the
step the default generator takes the run's state and hands it back after, so the draws are the run
generator's to the digit, a resumed run draws what the uninterrupted one would, and draws outside
a step (a network's initialisation) neither see nor move the run's stream.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch


def default_generator(device: torch.device) -> torch.Generator:
    """The generator `torch.rand(..., device=device)` draws from."""
    if device.type == "cuda":
        index = device.index if device.index is not None else torch.cuda.current_device()
        return torch.cuda.default_generators[index]
    if device.type != "cpu":
        raise ValueError(f"no default generator is known for device {device.type!r}")
    return torch.default_generator


@contextlib.contextmanager
def lent(generator: torch.Generator) -> Iterator[None]:
    """The default generator of `generator`'s device draws `generator`'s stream inside the block."""
    default = default_generator(generator.device)
    own = default.get_state()
    default.set_state(generator.get_state())
    try:
        yield
    finally:
        generator.set_state(default.get_state())
        default.set_state(own)

"""The stages of a training step, as torch.profiler labels: the loop marks the ray batch, the
backward pass and the optimizer step (workers/train/loop.py), the methods their sampler, main field,
background and losses. `leco bench-step` (bench/step_profile.py) reads each stage's share of a step
off these labels, off `host_read` the reads of a tensor's values into Python (`tolist` runs no
operator on the CPU, so only the label shows where CUDA would wait), and off `host_draw` the work
a CUDA run does on the host (a ray batch drawn by the prefetching thread of
workers/train/ray_batches.py), which waits for no device. Without a running profiler a label costs
about a microsecond and changes no value."""

from __future__ import annotations

from torch import Tensor
from torch.profiler import record_function

STAGES = ("ray_batch", "sampler", "field", "background", "losses", "backward", "optimizer")
PREFIX = "stage::"
HOST_READ = "sync::host_read"
HOST_DRAW = "host::draw"


def stage(name: str) -> record_function:
    """The label of one stage (a context manager); nested labels: the innermost one counts."""
    if name not in STAGES:
        raise ValueError(f"unknown stage {name!r}: one of {', '.join(STAGES)}")
    return record_function(PREFIX + name)


def host_read(values: Tensor) -> list:
    """`values.tolist()` under the `host_read` label: one wait for the device on CUDA."""
    with record_function(HOST_READ):
        return values.tolist()

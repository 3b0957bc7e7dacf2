"""The metrics row of the steps since the last one: rays and samples per second over the window's
training time, with the step's own loss parts and any evaluation beside them. The parts and the
window's sample count may be device tensors: the row reads them in one go."""

from __future__ import annotations

import resource

import torch
from torch import Tensor

from model.methods.parts import Parts, read_parts

# the window's summed samples per ray, read beside the parts
_SAMPLES = "__window_samples_per_ray"


def peak_memory_mb(device: torch.device) -> float:
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux reports KiB


class MetricsWindow:
    def __init__(self, global_batch: int):
        self.global_batch = global_batch
        self.clear()

    def clear(self) -> None:
        self.seconds, self.steps = 0.0, 0
        self.samples: float | Tensor = 0.0

    def add(self, seconds: float, parts: Parts) -> None:
        self.seconds += seconds
        self.steps += 1
        self.samples += parts.get("samples_per_ray", 0.0)

    def row(self, parts: Parts, device: torch.device) -> dict:
        """The window's rates, then clears it for the next."""
        read = read_parts({**parts, _SAMPLES: self.samples})
        samples = read.pop(_SAMPLES)
        rays = self.global_batch * self.steps / self.seconds
        row = {
            **read,
            "rays_per_s": rays,
            "samples_per_s": rays * samples / self.steps,
            "peak_memory_mb": peak_memory_mb(device),
        }
        self.clear()
        return row

"""The metrics row of the steps since the last one: rays and samples per second over the window's
training time, with the step's own loss parts and any evaluation beside them."""

from __future__ import annotations

import resource

import torch


def peak_memory_mb(device: torch.device) -> float:
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux reports KiB


class MetricsWindow:
    def __init__(self, global_batch: int):
        self.global_batch = global_batch
        self.clear()

    def clear(self) -> None:
        self.seconds, self.steps, self.samples = 0.0, 0, 0.0

    def add(self, seconds: float, parts: dict) -> None:
        self.seconds += seconds
        self.steps += 1
        self.samples += parts.get("samples_per_ray", 0.0)

    def row(self, parts: dict, device: torch.device) -> dict:
        """The window's rates, then clears it for the next."""
        rays = self.global_batch * self.steps / self.seconds
        row = {
            **parts,
            "rays_per_s": rays,
            "samples_per_s": rays * self.samples / self.steps,
            "peak_memory_mb": peak_memory_mb(device),
        }
        self.clear()
        return row

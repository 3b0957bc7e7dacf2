"""A run's networks and its optimizer per phase, both as its method (model/methods) says. Every rank
builds the networks from the same seed, so data-parallel replicas start identical."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, NamedTuple

import torch

from model.methods import Method, Networks
from model.methods.schedules import log_linear


@dataclass(frozen=True)
class LiveNetworks:
    """A method's networks as they are now, on the device they train on, with the scene box they
    render in: what validation and periodic evaluation read of a run."""

    method: Method
    models: Networks
    aabb: torch.Tensor
    device: torch.device


def build_models(method: Method, num_images: int, aabb: torch.Tensor, seed: int) -> Networks:
    torch.manual_seed(seed)
    return method.build(num_images, aabb)


def phase_parameters(method: Method, models: Networks, phase: str) -> list[torch.nn.Parameter]:
    params = [p for m in method.trained_modules(models, phase) for p in m.parameters()]
    return params + method.extra_parameters(models, phase)


def param_groups(
    method: Method, models: Networks, phase: str, params: list[torch.nn.Parameter]
) -> list[dict]:
    """Adam's parameter groups: the phase's rate first, then each network the method trains at a
    multiple of it (`lr_scale`, which the loop applies to the schedule's rate)."""
    scale_of = {
        id(p): scale for m, scale in method.lr_scales(models, phase) for p in m.parameters()
    }
    groups: dict[float, list[torch.nn.Parameter]] = {1.0: []}
    for p in params:
        groups.setdefault(scale_of.get(id(p), 1.0), []).append(p)
    return [{"params": ps, "lr_scale": scale} for scale, ps in groups.items() if ps]


class PhaseObjects(NamedTuple):
    params: list[torch.nn.Parameter]
    optimizer: torch.optim.Optimizer
    lr_at: Callable[[float], float]  # the phase's learning rate at a progress in [0, 1]


def build_optimizer(method: Method, models: Networks, phase: str) -> PhaseObjects:
    """Adam over what the phase trains, and its learning rate as a function of the phase's progress
    in [0, 1] (log-linear from the method's start to its final lr, constant without one). Progress
    counts steps or, under a wall-clock budget, training time (model/methods/schedules.py), so a
    budgeted run ends at its final lr too."""
    params = phase_parameters(method, models, phase)
    start, final = method.phase_lr(phase)
    # Fused: one kernel over every tensor instead of a loop over ~90 (4.0 -> 0.8 ms a step on 2 CPU
    # cores).
    optimizer = torch.optim.Adam(
        param_groups(method, models, phase, params),
        lr=start,
        fused=True,
        **method.adam_options(phase),
    )
    return PhaseObjects(params, optimizer, lambda progress: log_linear(start, final, progress))

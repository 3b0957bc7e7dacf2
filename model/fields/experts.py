"""Expert MLPs and the top-1 dispatch that routes each point to one of them."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from model.methods.stages import host_read


class Expert(nn.Module):
    """`layers` x Linear(W, W) + ReLU with the block input added back after layer `residual_at`
    (Switch-NeRF)."""

    def __init__(self, width: int, layers: int = 7, residual_at: int = 3):
        super().__init__()
        self.layers = nn.ModuleList(nn.Linear(width, width) for _ in range(layers))
        self.residual_at = residual_at

    def forward(self, x: Tensor) -> Tensor:
        h = x
        for i, layer in enumerate(self.layers):
            h = torch.relu(layer(h))
            if i == self.residual_at:
                h = h + x
        return h


def top1(logits: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Softmax over experts in fp32, then top-1: (probabilities (N, E), index (N,), chosen
    probability (N,)). Ties go to the lowest index (torch.max is deterministic about that)."""
    probs = torch.softmax(logits.float(), dim=-1)
    chosen, index = probs.max(dim=-1)
    return probs, index, chosen


def capacity_keep(
    index: Tensor, chosen: Tensor, num_experts: int, capacity_factor: float | None
) -> Tensor:
    """Which points an expert accepts. With a capacity factor, each expert takes at most
    ceil(factor * N / E) points and drops its least confident overflow (their output is zero)."""
    keep = torch.ones_like(index, dtype=torch.bool)
    if capacity_factor is None or len(index) == 0:
        return keep
    capacity = math.ceil(capacity_factor * len(index) / num_experts)
    for e in range(num_experts):
        members = torch.nonzero(index == e).squeeze(1)
        if len(members) > capacity:
            order = torch.argsort(chosen[members], descending=True, stable=True)
            keep[members[order[capacity:]]] = False
    return keep


def group_sizes(index: Tensor, groups: int) -> Tensor:
    """How many entries of `index` hold each of 0 .. groups - 1: bincount's answer, without the
    host read bincount makes to size its output."""
    return torch.zeros(groups, dtype=torch.long, device=index.device).index_add_(
        0, index, torch.ones_like(index)
    )


def dispatch(experts: nn.ModuleList, h: Tensor, index: Tensor, keep: Tensor) -> Tensor:
    """Run each expert on exactly its points (gather, compute, scatter); dropped points stay zero.

    Sort and segment: one stable sort groups the points by expert (each group in its points' order,
    so every expert multiplies the same rows in the same order as a gather per expert would) and
    one host read of the group sizes cuts it, where a gather per expert waits on the device once
    per expert."""
    out = h.new_zeros(h.shape[0], h.shape[1])
    n = len(experts)
    group = index.masked_fill(~keep, n)  # dropped points sort last, into no expert's group
    order = torch.argsort(group, stable=True)
    sizes = host_read(group_sizes(group, n + 1))[:n]
    rows = h[order[: sum(sizes)]]
    results = [
        expert(chunk).to(out.dtype)
        for expert, chunk in zip(experts, rows.split(sizes))
        if len(chunk)
    ]
    if results:
        out = out.index_copy(0, order[: sum(sizes)], torch.cat(results))
    return out

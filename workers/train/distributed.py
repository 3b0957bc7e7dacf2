"""Plain data parallel by hand: every rank holds the whole model and averages gradients with one
all-reduce. Top-1 experts leave some parameters without a gradient on some ranks, so missing
gradients count as zeros (DDP would need find_unused_parameters for that)."""

from __future__ import annotations

import torch
import torch.distributed as dist
from torch import Tensor, nn


def is_distributed() -> bool:
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def average_gradients(params: list[nn.Parameter]) -> None:
    """A parameter no rank has a gradient for keeps none, so Adam leaves it alone as on one rank
    (S+Prop's proposals between their updates); one that some rank lacks counts as zero there."""
    if not is_distributed():
        return
    present = torch.tensor(
        [p.grad is not None for p in params], dtype=torch.uint8, device=params[0].device
    )
    dist.all_reduce(present, op=dist.ReduceOp.MAX)
    params = [p for p, seen in zip(params, present.tolist()) if seen]
    if not params:
        return
    grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in params]
    flat = torch.cat([g.reshape(-1) for g in grads])
    dist.all_reduce(flat)
    flat /= dist.get_world_size()
    offset = 0
    for p in params:
        n = p.numel()
        p.grad = flat[offset : offset + n].view_as(p).clone()
        offset += n


def any_rank(flag: bool, device: torch.device) -> bool:
    """True on every rank when `flag` is true on any rank (a non-finite loss, the budget spent)."""
    return any_rank_each([flag], device)[0]


def any_rank_each(flags: list[bool], device: torch.device) -> list[bool]:
    """`any_rank` for several flags in one all-reduce (the per-step checks share a collective)."""
    if not is_distributed():
        return list(flags)
    values = torch.tensor([1.0 if f else 0.0 for f in flags], device=device)
    dist.all_reduce(values, op=dist.ReduceOp.MAX)
    return [bool(v > 0) for v in values.tolist()]


def any_rank_tensor(flag: Tensor) -> Tensor:
    """`any_rank` for a 0-dim float flag that stays on the device (0.0 or 1.0): the largest over
    ranks, with no host read."""
    if is_distributed():
        dist.all_reduce(flag, op=dist.ReduceOp.MAX)
    return flag

"""The non-finite guard, kept on the device: a step whose loss or gradients hold a NaN or Inf is
skipped by the fused Adam (`found_inf`), and the streak of skipped steps is counted on the device
and read only when the loop logs, so no step waits for the verdict."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from model.methods.stages import host_read


def nonfinite(loss: Tensor, params: list[nn.Parameter]) -> Tensor:
    """1.0 when the loss or any gradient holds a NaN or Inf, else 0.0 (a 0-dim float tensor, as
    Adam's `found_inf` takes it). One foreach pass, not a check per tensor: a NaN or Inf makes its
    tensor's norm non-finite. A gradient so large that its norm overflows float32 (entries near
    1e19) counts as non-finite too; that step would be useless anyway."""
    grads = [p.grad for p in params if p.grad is not None]
    norms = [loss, *torch._foreach_norm(grads)] if grads else [loss]
    values = torch.stack([n.detach().float().reshape(()) for n in norms])
    return (~torch.isfinite(values)).any().float()


class NonfiniteStreak:
    """Consecutive skipped steps, on the device: the streak running now and the longest since the
    last read."""

    def __init__(self, start: int, device: torch.device):
        self.current = torch.tensor(start, dtype=torch.long, device=device)
        self.worst = self.current.clone()

    def add(self, skipped: Tensor) -> None:
        self.current = torch.where(skipped > 0, self.current + 1, torch.zeros_like(self.current))
        self.worst = torch.maximum(self.worst, self.current)

    def read(self) -> tuple[int, int]:
        """(longest streak since the last read, the streak running now): one host read. The
        running streak carries into the next window."""
        worst, current = host_read(torch.stack([self.worst, self.current]))
        self.worst = self.current.clone()
        return int(worst), int(current)

    def running(self) -> int:
        """The streak running now (a checkpoint keeps it), without ending the window."""
        return int(self.current)

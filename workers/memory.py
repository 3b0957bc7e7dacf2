"""Training memory that depends on the method: the bytes autograd keeps for the backward pass of one
step.

On a GPU `torch.cuda.max_memory_allocated` answers directly. On a CPU the process's peak RSS is
dominated by the runtime, the scene and the weights, which every method shares; what the samplers
change is how many per-sample activations a step keeps, and those are exactly the tensors autograd
saves."""

from __future__ import annotations

import torch


class SavedTensorBytes:
    """Context manager: the unique storages autograd saves while it is open (weights included)."""

    def __init__(self) -> None:
        self.storages: dict[int, int] = {}

    def _pack(self, tensor: torch.Tensor) -> torch.Tensor:
        storage = tensor.untyped_storage()
        self.storages[storage.data_ptr()] = storage.nbytes()
        return tensor

    def __enter__(self) -> "SavedTensorBytes":
        self._hooks = torch.autograd.graph.saved_tensors_hooks(self._pack, lambda tensor: tensor)
        self._hooks.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._hooks.__exit__(*exc)

    @property
    def megabytes(self) -> float:
        return sum(self.storages.values()) / 2**20

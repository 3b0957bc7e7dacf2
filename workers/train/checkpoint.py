"""What a checkpoint holds and how a rank comes back to it. A checkpoint is everything the next step
depends on: the progress counters, the networks, the method's own state (a grid, a frozen O), the
optimizer, the ray sampler's position and every rank's generator, so a resumed run continues the
run it was; and the config and resolved profile it trained with, so a resume never picks up a
changed default (TrainConfig.pinned)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from model.methods import Method, Networks
from model.methods.base import method_state
from workers.config import TrainConfig
from workers.train.distributed import is_distributed
from workers.train.ray_batches import RayBatches

STATE_FILE = "state.pt"


@dataclass
class TrainingState:
    """What changes while a rank trains: its counters, networks, method state, rays and draws."""

    progress: dict[str, Any]
    models: Networks
    method: Method
    sampler: RayBatches
    generator: torch.Generator


def generator_states(generator: torch.Generator, world_size: int) -> list[torch.Tensor]:
    """Every rank's generator state, gathered (a collective: every rank takes part)."""
    state = generator.get_state()
    if not is_distributed():
        return [state]
    import torch.distributed as dist

    gathered: list[Any] = [None] * world_size
    dist.all_gather_object(gathered, state)
    return gathered


def snapshot(
    state: TrainingState,
    optimizer: torch.optim.Optimizer,
    generators: list[torch.Tensor],
    cfg: TrainConfig,
) -> dict:
    """The checkpoint's contents (rank 0's networks; `generators`: every rank's)."""
    return {
        "progress": state.progress,
        "models": state.models.state_dict(),
        "method": state.method.state_dict(),
        "optimizer": optimizer.state_dict(),
        "sampler": state.sampler.state_dict(),
        "generators": generators,
        "torch_rng": torch.get_rng_state(),
        "config": cfg.model_dump(),
        "resolved_profile": cfg.resolved_profile().model_dump(mode="json"),
    }


def load_snapshot(folder: Path) -> dict:
    # On the CPU: RNG states must stay CPU tensors; load_state_dict copies the rest onto the device.
    return torch.load(Path(folder) / STATE_FILE, map_location="cpu", weights_only=False)


def restore_networks(state: TrainingState, saved: dict, device: torch.device) -> None:
    """Counters, networks and method state back from a checkpoint (the optimizer comes back once
    its phase has made it: restore_draws)."""
    state.progress = saved["progress"]
    state.models.load_state_dict(saved["models"])
    state.method.load_state_dict(method_state(saved))
    state.models.to(device)


def restore_draws(
    state: TrainingState, saved: dict, optimizer: torch.optim.Optimizer, rank: int
) -> None:
    """The optimizer, the ray sampler and the random draws back (the lr follows from progress)."""
    optimizer.load_state_dict(saved["optimizer"])
    state.sampler.load_state_dict(saved["sampler"])
    states = saved["generators"]
    state.generator.set_state(states[rank] if rank < len(states) else states[0])
    torch.set_rng_state(saved["torch_rng"])


def save_final(state: TrainingState, cfg: TrainConfig, final: Path) -> None:
    """final/: the finished networks with the config and profile they trained with, the method's own
    files (LeCO's occupancy network) and the progress counters."""
    final.mkdir(parents=True, exist_ok=True)
    torch.save(
        {
            "models": state.models.state_dict(),
            "method": state.method.state_dict(),
            "progress": state.progress,
            "config": cfg.model_dump(),
            "resolved_profile": cfg.resolved_profile().model_dump(mode="json"),
        },
        final / "models.pt",
    )
    state.method.save_final(final)
    (final / "progress.json").write_text(json.dumps(state.progress, indent=1))

"""Early ray termination for image renders (Instant-NGP's and nerfacc's test-time marching): the
field runs on each ray's samples a block at a time, front to back, and a ray stops once the light
reaching it falls below `eps`. A sample never run lies behind transmittance < eps, so its weight,
and the colour it could add, is below eps; the samples that were run composite exactly as before.

Training keeps every sample (the cost a sampler is charged for is what it sends the main network);
this only makes validation, renders and exports of a young, mostly occupied grid affordable."""

from __future__ import annotations

from dataclasses import fields
from typing import Callable

import torch
from torch import Tensor

from model.fields.output import FieldOutput
from model.render.samples import PackedSamples

# (sample indices) -> the field's output at those samples
FieldOn = Callable[[Tensor], FieldOutput]


def rank_along_ray(ray_index: Tensor, num_rays: int) -> Tensor:
    """Each packed sample's position along its ray (0 for a ray's first sample)."""
    counts = torch.bincount(ray_index, minlength=num_rays)
    first = torch.cumsum(counts, 0) - counts
    return torch.arange(len(ray_index), device=ray_index.device) - first[ray_index]


def concat_outputs(parts: list[FieldOutput]) -> FieldOutput:
    return FieldOutput(
        *(torch.cat([getattr(p, f.name) for p in parts]) for f in fields(FieldOutput))
    )


def front_to_back(
    field_on: FieldOn,
    samples: PackedSamples,
    num_rays: int,
    eps: float,
    block: int = 16,
) -> tuple[FieldOutput | None, PackedSamples]:
    """The field's outputs on the samples each ray reaches with transmittance >= eps, and those
    samples (packed, in order). eps = 0 runs every sample in one pass."""
    if len(samples) == 0:
        return None, samples
    if eps <= 0:
        return field_on(torch.arange(len(samples), device=samples.starts.device)), samples
    rank = rank_along_ray(samples.ray_index, num_rays)
    depth = torch.zeros(num_rays, dtype=torch.float64, device=samples.starts.device)
    stop_depth = -torch.log(torch.tensor(eps, dtype=torch.float64))
    ran: list[Tensor] = []
    outs: list[FieldOutput] = []
    for first in range(0, int(rank.max()) + 1, block):
        alive = depth < stop_depth  # T = exp(-depth) >= eps
        pick = (rank >= first) & (rank < first + block) & alive[samples.ray_index]
        index = torch.nonzero(pick).squeeze(1)
        if len(index) == 0:
            if not bool(alive.any()):
                break
            continue
        out = field_on(index)
        tau = (out.sigma.detach().double() * samples.deltas[index].double()).clamp(min=0)
        depth.index_add_(0, samples.ray_index[index], tau)
        ran.append(index)
        outs.append(out)
    index = torch.cat(ran)
    order = torch.argsort(index)  # back to packed order: grouped by ray, increasing t
    out = concat_outputs(outs)
    out = FieldOutput(*(getattr(out, f.name)[order] for f in fields(FieldOutput)))
    index = index[order]
    return out, PackedSamples(samples.starts[index], samples.ends[index], samples.ray_index[index])

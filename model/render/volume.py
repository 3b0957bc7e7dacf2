"""Volume rendering in packed form (flat samples + ray index, sorted by ray) and batched form (rays
x samples).

Transmittance is accumulated in log space (T_i = exp(-sum_{j<i} sigma_j delta_j)) in float64 with
the optical depth of one sample capped at TAU_MAX, so no finite input makes NaN or Inf, and packed
and batched agree. Whatever transmittance is left at the end of a ray's foreground samples shows the
background."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

TAU_MAX = 110.0  # exp(-110) rounds to 0 in float32: a sample this opaque is exactly opaque


@dataclass
class Rendered:
    rgb: Tensor  # (R, 3)
    # (R,) expected foreground distance, weighted by opacity (0 where the ray is empty)
    depth: Tensor
    opacity: Tensor  # (R,) sum of weights, in [0, 1]
    weights: Tensor  # packed (S,) or batched (R, N)
    transmittance: Tensor  # (R,) left after the foreground: the background's share


def packed_optical_depth(
    sigma: Tensor, deltas: Tensor, ray_index: Tensor, num_rays: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Per-sample tau_i, the optical depth before each sample (sum_{j<i} tau_j on its ray) and per
    ray."""
    tau = (sigma.double() * deltas.double()).clamp(0.0, TAU_MAX)
    total = torch.zeros(num_rays, dtype=torch.float64, device=tau.device).index_add_(
        0, ray_index, tau
    )
    return tau, exclusive_cumsum_per_ray(tau, ray_index, num_rays), total


def exclusive_cumsum_per_ray(values: Tensor, ray_index: Tensor, num_rays: int) -> Tensor:
    """sum_{j<i} values_j over the samples of sample i's ray (packed, grouped by ray)."""
    inclusive = values.cumsum(0)
    start = torch.zeros(num_rays, dtype=values.dtype, device=values.device)
    if len(values):
        # Cumulative sum at the first sample of each ray, so each ray's sum starts from zero.
        first = torch.ones_like(ray_index, dtype=torch.bool)
        first[1:] = ray_index[1:] != ray_index[:-1]
        start[ray_index[first]] = (inclusive - values)[first]
    return inclusive - values - start[ray_index]


def packed_transmittance(sigma: Tensor, deltas: Tensor, ray_index: Tensor, num_rays: int) -> Tensor:
    """T_i, the light that reaches each sample (1 at a ray's first sample)."""
    return torch.exp(-packed_optical_depth(sigma, deltas, ray_index, num_rays)[1]).to(sigma.dtype)


def packed_weights(
    sigma: Tensor, deltas: Tensor, ray_index: Tensor, num_rays: int
) -> tuple[Tensor, Tensor]:
    """Per-sample weights T_i alpha_i and per-ray remaining transmittance; samples grouped by ray in
    order."""
    tau, exclusive, total = packed_optical_depth(sigma, deltas, ray_index, num_rays)
    alpha = -torch.expm1(-tau)
    weights = (torch.exp(-exclusive) * alpha).to(sigma.dtype)
    return weights, torch.exp(-total).to(sigma.dtype)


def batched_weights(sigma: Tensor, deltas: Tensor) -> tuple[Tensor, Tensor]:
    tau = (sigma.double() * deltas.double()).clamp(0.0, TAU_MAX)
    exclusive = tau.cumsum(-1) - tau
    weights = torch.exp(-exclusive) * -torch.expm1(-tau)
    return weights.to(sigma.dtype), torch.exp(-tau.sum(-1)).to(sigma.dtype)


def composite_packed(
    sigma: Tensor,
    rgb: Tensor,
    t_mid: Tensor,
    deltas: Tensor,
    ray_index: Tensor,
    num_rays: int,
    background_rgb: Tensor,
) -> Rendered:
    """background_rgb (R, 3) (or broadcastable) is what the remaining transmittance sees."""
    weights, remaining = packed_weights(sigma, deltas, ray_index, num_rays)
    colour = torch.zeros(num_rays, 3, dtype=rgb.dtype, device=rgb.device).index_add_(
        0, ray_index, weights[:, None] * rgb
    )
    depth = torch.zeros(num_rays, dtype=t_mid.dtype, device=t_mid.device).index_add_(
        0, ray_index, weights * t_mid
    )
    opacity = torch.zeros(num_rays, dtype=weights.dtype, device=weights.device).index_add_(
        0, ray_index, weights
    )
    return Rendered(
        colour + remaining[:, None] * background_rgb, depth, opacity, weights, remaining
    )


def composite_batched(
    sigma: Tensor, rgb: Tensor, t_mid: Tensor, deltas: Tensor, background_rgb: Tensor
) -> Rendered:
    weights, remaining = batched_weights(sigma, deltas)
    colour = (weights[..., None] * rgb).sum(-2) + remaining[:, None] * background_rgb
    return Rendered(colour, (weights * t_mid).sum(-1), weights.sum(-1), weights, remaining)

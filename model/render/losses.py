"""Losses of LeCO-NeRF (paper section 3.3) and Switch-NeRF, with the parts the dashboard shows."""

from __future__ import annotations

import torch
from torch import Tensor

from model.fields.experts import group_sizes
from model.render.samples import PackedSamples
from model.render.volume import exclusive_cumsum_per_ray

EPS = 1e-10


def dispatch_fractions(probs: Tensor, index: Tensor) -> tuple[Tensor, Tensor]:
    """f: fraction of points sent to each expert (not differentiable); p: mean gate value per
    expert."""
    f = group_sizes(index, probs.shape[1]).float() / max(len(index), 1)
    return f, probs.mean(dim=0) if len(probs) else probs.new_zeros(probs.shape[1])


def balance_loss(probs: Tensor, index: Tensor) -> Tensor:
    """Switch Transformer balance loss L_b = E * sum_i f_i p_i: 1 when the experts share points
    equally."""
    f, p = dispatch_fractions(probs, index)
    return probs.shape[1] * (f * p).sum()


def imbalanced_gate_loss(probs: Tensor, index: Tensor, v: float) -> Tensor:
    """L_g = (n + v) (f_e p_e / v + sum_i f_i p_i): E_e counts as v virtual experts (Eq. 1).
    The empty expert is the last column; the optimum 1.0 sends it v / (n + v) of the points."""
    f, p = dispatch_fractions(probs, index)
    n = probs.shape[1] - 1
    return (n + v) * (f[n] * p[n] / v + (f[:n] * p[:n]).sum())


def density_loss(probs: Tensor, index: Tensor, sigma: Tensor) -> Tensor:
    """L_d = (|Y| / |X|) sum_X g sigma / sum_Y g sigma, sigma detached (Eq. 2). X: points sent to
    E_e, g their E_e gate; Y: points sent to scene experts, g the sum of the n scene gates. Zero
    (with a gradient path) when X or Y is empty: there is no ratio to push down. X and Y are
    gathered (two host reads, in phase 1 only): a masked sum adds the same values in another order,
    and phase 1's runs would no longer reproduce bit for bit."""
    n = probs.shape[1] - 1
    empty = index == n
    num_x, num_y = int(empty.sum()), int((~empty).sum())
    sigma = sigma.detach().float()
    if num_x == 0 or num_y == 0:
        return probs.sum() * 0.0
    weighted_x = (probs[empty, n] * sigma[empty]).sum()
    weighted_y = (probs[~empty, :n].sum(dim=-1) * sigma[~empty]).sum()
    return (num_y / num_x) * weighted_x / (weighted_y + EPS)


def visibility_loss(probs: Tensor, weights: Tensor) -> Tensor:
    """L_v = -sum_i w_i log(1 - p_e,i) / sum_i w_i, w_i = T_i alpha_i detached: the samples a ray
    actually shows are sent away from E_e in proportion to how much they show (not in the paper)."""
    w = weights.detach().float().reshape(-1)
    not_empty = (1.0 - probs[:, -1]).clamp(min=EPS)
    return -(w * torch.log(not_empty)).sum() / (w.sum() + EPS)


def distortion_loss(
    weights: Tensor, samples: PackedSamples, near: Tensor, far: Tensor, num_rays: int
) -> Tensor:
    """mip-NeRF 360's L_dist (Barron et al. 2022, Eq. 15), mean over rays: sum_ij w_i w_j
    |s_i - s_j| + 1/3 sum_i w_i^2 (s_i+1 - s_i), with s each sample's distance normalised to its
    ray's foreground segment. It is least when a ray's weight sits in one short interval, so it
    charges the semi-transparent fog and floaters a field fits to views it cannot generalise from.
    The double sum is 2 sum_i w_i (m_i W_<i - S_<i) with W, S the running sums of w and w m."""
    if len(samples) == 0:
        return weights.sum() * 0.0
    ray = samples.ray_index
    length = (far - near).clamp(min=EPS)[ray]
    start = (samples.starts - near[ray]) / length
    end = (samples.ends - near[ray]) / length
    w, mid = weights.double(), (0.5 * (start + end)).double()
    before = exclusive_cumsum_per_ray(w, ray, num_rays)
    moment = exclusive_cumsum_per_ray(w * mid, ray, num_rays)
    pairs = 2.0 * w * (mid * before - moment)
    inside = w**2 * (end - start).double() / 3.0
    return ((pairs + inside).sum() / max(num_rays, 1)).to(weights.dtype)


def rendering_loss(rgb: Tensor, target: Tensor) -> Tensor:
    """Mean squared colour error over rays (the paper sums; the mean keeps the scale
    batch-independent)."""
    return ((rgb.float() - target.float()) ** 2).mean()


def gate_statistics(
    probs: Tensor, index: Tensor, sigma: Tensor, alpha: Tensor | None = None
) -> dict[str, Tensor]:
    """The paper's Fig. 5 numbers, as 0-dim tensors: share of points per expert and to E_e, mean
    density (and alpha) of E_e points against scene-expert points, and their ratio. Missing groups
    read as NaN, never a crash."""
    n = probs.shape[1] - 1
    f, _ = dispatch_fractions(probs, index)
    empty = index == n
    stats = {f"fraction_expert_{i}": f[i] for i in range(n)}
    stats["fraction_empty"] = f[n]
    for name, values in (("density", sigma), ("alpha", alpha)):
        if values is None:
            continue
        values = values.detach().float()
        # masked means: 0 / 0 is NaN where a group is empty
        e = values.masked_fill(~empty, 0.0).sum() / empty.sum()
        s = values.masked_fill(empty, 0.0).sum() / (~empty).sum()
        stats[f"{name}_empty"], stats[f"{name}_scene"] = e, s
        stats[f"{name}_ratio"] = torch.where(s > 0, e / s, torch.full_like(s, float("nan")))
    return stats

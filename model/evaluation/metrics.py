"""Image and occupancy metrics: PSNR, SSIM (11x11 Gaussian, sigma 1.5; smaller on smaller images),
occupancy accuracy/precision/recall/F1."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor


def psnr(pred: Tensor, target: Tensor) -> float:
    """Peak signal-to-noise ratio for colours in [0, 1]; inf for identical images."""
    mse = float(((pred.float() - target.float()) ** 2).mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def _gaussian_window(size: int = 11, sigma: float = 1.5) -> Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    return (g[:, None] * g[None, :]).float()


def ssim(pred: Tensor, target: Tensor, k1: float = 0.01, k2: float = 0.03) -> float:
    """Mean SSIM of two (H, W, 3) images in [0, 1] (valid-region filtering, as in the NeRF papers'
    code)."""
    x = pred.float().permute(2, 0, 1)[None]
    y = target.float().permute(2, 0, 1)[None]
    # An image narrower than the 11-pixel window (a small view downscaled, then halved by the
    # validation protocol) takes the largest odd window that fits instead of failing.
    size = min(11, (min(x.shape[-2:]) - 1) // 2 * 2 + 1)
    window = _gaussian_window(size).to(x.device)[None, None].expand(3, 1, size, size)
    blur = lambda z: F.conv2d(z, window, groups=3)
    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x**2
    var_y = blur(y * y) - mu_y**2
    cov = blur(x * y) - mu_x * mu_y
    c1, c2 = k1**2, k2**2
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / (
        (mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2)
    )
    return float(ssim_map.mean())


def occupancy_metrics(
    predicted: Tensor, reference: Tensor, mask: Tensor | None = None
) -> dict[str, float]:
    """Accuracy, precision, recall, F1 of a predicted boolean grid against a reference grid
    (optionally only where `mask` is true, e.g. the region the validation rays observe)."""
    p, r = predicted.bool().reshape(-1), reference.bool().reshape(-1)
    if mask is not None:
        keep = mask.bool().reshape(-1)
        p, r = p[keep], r[keep]
    tp = int((p & r).sum())
    fp = int((p & ~r).sum())
    fn = int((~p & r).sum())
    total = max(len(p), 1)
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / (tp + fn) if tp + fn else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {
        "accuracy": (total - fp - fn) / total,
        "precision": precision,
        "recall": recall,
        "f1": f1,
        "predicted_occupied_fraction": float(p.float().mean()) if len(p) else 0.0,
        "reference_occupied_fraction": float(r.float().mean()) if len(r) else 0.0,
    }

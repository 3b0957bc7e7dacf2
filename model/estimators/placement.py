"""O places the main network's samples (guided.placement): the part of a proposal network that LeCO
lacked.

O decides which coarse bins of a ray may hold a surface (keep/drop, section 3.4). With a placement
head it also gives each coarse bin a density; composited along the ray, those densities are a
histogram of where the ray's weight lies. A fixed budget of samples per hit ray is then drawn by
inverse CDF over the kept bins only, so a bin that holds half of a ray's weight gets about half of
its samples, where the split sampler gave every kept bin the same `split`. The head learns as
mip-NeRF 360's proposals do: its histogram must bound the main network's detached weights from above
(eq. 13), here at the resolution of the coarse bins.

Kept bins need not be contiguous. Samples are drawn on the kept bins laid end to end (a coordinate s
that skips dropped bins), so no interval straddles a dropped bin: each sample's mid-point is mapped
back to t, and its length in s is its delta (dropped bins hold no density, as O says)."""

from __future__ import annotations

import torch
from torch import Tensor

from model.render.accounting import sample_bins
from model.render.noise import Noise
from model.render.samples import PackedSamples, invert_cdf

EPS = 1e-7


def placed_samples(
    edges: Tensor, keep: Tensor, weights: Tensor, n: int, noise: Noise | None
) -> PackedSamples:
    """Exactly n samples per ray (rows of `edges` (R, B + 1)), sorted along it, inside its kept bins
    (`keep` (R, B), at least one per row), distributed like `weights` (R, B) (>= 0; padding already
    added) over them. Deterministic (CDF levels at (j + 0.5) / n) without a noise, stratified
    and jittered with one."""
    r, b = keep.shape
    width = (edges[:, 1:] - edges[:, :-1]) * keep
    # kept bins end to end
    s_edges = torch.cat([torch.zeros_like(width[:, :1]), width.cumsum(-1)], -1)
    mass = weights.clamp(min=0) * keep
    # no weight: by length
    mass = torch.where(mass.sum(-1, keepdim=True) > 0, mass, keep.to(mass.dtype) * width)
    cumulative = torch.cat([torch.zeros_like(mass[:, :1]), mass.cumsum(-1)], -1)
    cdf = cumulative / cumulative[:, -1:].clamp(min=1e-30)
    if noise is None:
        u = torch.linspace(0.0, 1.0, n + 1, device=edges.device).expand(r, n + 1).contiguous()
    else:
        u = (
            torch.arange(n + 1, device=edges.device) + noise.rand(r, n + 1, device=edges.device)
        ) / (n + 1)
    s = invert_cdf(s_edges, cdf, u.to(cdf.dtype))
    mid_s, delta = 0.5 * (s[:, 1:] + s[:, :-1]), s[:, 1:] - s[:, :-1]
    # The kept bin holding each mid-point; ties go to the last bin starting there, which is the kept
    # one (a dropped bin is zero-long in s, so the kept bin after it starts at the same s).
    bin_ = (torch.searchsorted(s_edges.contiguous(), mid_s.contiguous(), right=True) - 1).clamp(
        0, b - 1
    )
    t_mid = edges.gather(1, bin_) + (mid_s - s_edges.gather(1, bin_))
    ray = torch.arange(r, device=edges.device).repeat_interleave(n)
    t_mid, delta = t_mid.reshape(-1), delta.reshape(-1)
    return PackedSamples(t_mid - 0.5 * delta, t_mid + 0.5 * delta, ray)


WITHIN = ("uniform", "linear", "volume")  # guided.placement_within
SUBBINS = 4  # sub-bins per coarse bin that a non-uniform within-bin shape is drawn at


def within_bin_shares(
    kind: str, mass: Tensor, sigma: Tensor, edges: Tensor, k: int = SUBBINS
) -> Tensor:
    """(R, B, k): how each coarse bin's mass splits over its k equal sub-bins (each row sums to 1).
    uniform: evenly (one histogram bin, one flat density). linear: a density that varies linearly
    across the bin, from the mean with the bin in front to the mean with the bin behind (`mass` /
    width, dropped bins 0, the ray's ends flat), rescaled to keep the bin's mass. volume: the weight
    a constant density `sigma` (R, B) puts along the bin by volume rendering (eq. 3), which is the
    shape O's histogram already assumes: an opaque bin's weight sits at its front, a faint one's
    spreads evenly."""
    r, b = mass.shape
    x = (torch.arange(k, device=mass.device, dtype=mass.dtype) + 0.5) / k
    if kind == "uniform":
        return torch.full((r, b, k), 1.0 / k, device=mass.device, dtype=mass.dtype)
    width = (edges[:, 1:] - edges[:, :-1]).to(mass.dtype)
    if kind == "linear":
        d = mass / width.clamp(min=1e-30)
        front = torch.cat([d[:, :1], d[:, :-1]], -1)
        behind = torch.cat([d[:, 1:], d[:, -1:]], -1)
        a, z = 0.5 * (front + d), 0.5 * (d + behind)
        profile = a[..., None] + (z - a)[..., None] * x
        total = profile.sum(-1, keepdim=True)
        return torch.where(
            total > 0, profile / total.clamp(min=1e-30), torch.full_like(profile, 1.0 / k)
        )
    if kind == "volume":
        tau = (sigma.to(mass.dtype) * width).clamp(min=0, max=60.0)[..., None]
        steps = torch.arange(k + 1, device=mass.device, dtype=mass.dtype) / k
        through = torch.exp(-tau * steps)  # transmittance from the bin's front to each sub-bin edge
        share = (through[..., :-1] - through[..., 1:]) / (1 - through[..., -1:]).clamp(min=1e-30)
        faint = tau < 1e-4  # no measurable absorption: evenly, as the limit of the shape
        return torch.where(faint, torch.full_like(share, 1.0 / k), share)
    raise ValueError(f"within-bin shape {kind!r}: choose one of {', '.join(WITHIN)}")


def subdivided(
    edges: Tensor, keep: Tensor, mass: Tensor, shares: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """The bins cut into k equal sub-bins, each taking its share (R, B, k) of its bin's mass and its
    bin's keep: (edges (R, B * k + 1), keep (R, B * k), mass (R, B * k)) for `placed_samples`."""
    r, b, k = shares.shape
    steps = torch.arange(k, device=edges.device, dtype=edges.dtype) / k
    starts = edges[:, :-1, None] + (edges[:, 1:] - edges[:, :-1])[..., None] * steps
    fine_edges = torch.cat([starts.reshape(r, b * k), edges[:, -1:]], -1)
    fine_keep = keep[..., None].expand(r, b, k).reshape(r, b * k)
    return fine_edges, fine_keep, (mass[..., None] * shares).reshape(r, b * k)


def confident_bins(keep: Tensor, weights: Tensor, min_share: float) -> Tensor:
    """The kept bins (R, B) holding at least `min_share` of their ray's kept histogram `weights` (R,
    B); a ray where none does keeps its heaviest kept bin, and a ray without any weight keeps them
    all, so every ray that had a bin still has one."""
    if min_share <= 0:
        return keep
    mass = weights * keep
    total = mass.sum(-1, keepdim=True)
    # no weight: keep all
    share = torch.where(total > 0, mass / total.clamp(min=1e-30), torch.ones_like(mass))
    heaviest = torch.zeros_like(keep).scatter_(1, mass.argmax(-1, keepdim=True), True) & keep
    return (keep & (share >= min_share)) | heaviest


def explored(keep: Tensor, mass: Tensor, edges: Tensor, share: float) -> tuple[Tensor, Tensor]:
    """Every bin of each ray (R, B) may get a sample: the bins O dropped together receive `share` of
    the ray's mass (`mass` (R, B) over the kept bins, padding included), spread over them by length,
    so about `share` of the main samples look where O says nothing is, as a proposal's histogram
    padding does. A surface O dropped can then catch weight, and the online learner (which learns
    only from sampled bins) can teach O to keep it. Returns the new keep (all True) and mass; rays
    that keep every bin are unchanged."""
    if share <= 0:
        return keep, mass
    kept_mass = (mass * keep).sum(-1, keepdim=True)
    length = (edges[:, 1:] - edges[:, :-1]) * ~keep
    dropped = length.sum(-1, keepdim=True)
    spread = share / (1 - share) * kept_mass * length / dropped.clamp(min=1e-30)
    return torch.ones_like(keep), torch.where(keep, mass, spread)


def bin_mass(
    samples: PackedSamples, weights: Tensor, near: Tensor, far: Tensor, bins: int
) -> Tensor:
    """(R, bins) the main network's (detached) render weight summed in each coarse bin of each
    ray."""
    flat = samples.ray_index * bins + sample_bins(samples, near, far, bins)
    mass = torch.zeros(len(near) * bins, dtype=weights.dtype, device=weights.device)
    return mass.index_add_(0, flat, weights.detach()).reshape(len(near), bins)


def placement_loss(
    proposal: Tensor, samples: PackedSamples, weights: Tensor, near: Tensor, far: Tensor
) -> Tensor:
    """mip-NeRF 360's interlevel loss (eq. 13) on the coarse bins: max(0, w - w_O)^2 / w, where w is
    the main network's weight in a bin and w_O the placement histogram's (`proposal` (R, B), with
    gradient), averaged over every bin of every ray. Only O learns from it: the main weights are
    detached."""
    main = bin_mass(samples, weights, near, far, proposal.shape[1]).float()
    excess = (main - proposal.float()).clamp(min=0)
    return (excess**2 / (main + EPS)).mean()

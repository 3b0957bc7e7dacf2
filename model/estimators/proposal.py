"""Proposal sampling in plain PyTorch (mip-NeRF 360; nerfacc's PropNetEstimator and nerfstudio's
ProposalNetworkSampler work this way): stratified samples for the first proposal network, then level
by level the next samples drawn by inverse CDF from the previous level's (annealed) weights, the
main network last. The proposals learn only from the interlevel loss, a histogram upper bound
against the main network's detached weights (mip-NeRF 360, eq. 13)."""

from __future__ import annotations

import torch
from torch import Tensor

from model.render.noise import Noise
from model.render.samples import invert_cdf

EPS = 1e-7


def anneal_power(step: int | None, steps: int, slope: float) -> float:
    """nerfstudio's weight annealing: the exponent on proposal weights rises from 0 (uniform) to 1
    over `steps` along b x / ((b - 1) x + 1); 1 outside training (`step` None)."""
    if step is None or steps == 0:
        return 1.0
    x = min(step / steps, 1.0)
    return slope * x / ((slope - 1.0) * x + 1.0)


def pdf_edges(
    edges: Tensor,
    weights: Tensor,
    n: int,
    noise: Noise | None,
    anneal: float = 1.0,
    padding: float = 0.01,
    support: Tensor | None = None,
) -> Tensor:
    """(R, n + 1) sorted edges of n new intervals placed by the piecewise-constant pdf of `weights`
    (R, M) over `edges` (R, M + 1): u at n + 1 stratified levels of the CDF (jittered with a
    noise), each mapped back to t. `padding` is added to every weight first (nerfstudio's
    histogram padding), so no bin is unreachable; with `support` (R, M) bool, only to the bins in
    it, and the others get nothing (zero-long bins of a kept axis, where a sample would be
    wasted)."""
    w = weights.detach().float().clamp(min=0) ** anneal + padding
    inside = torch.ones_like(w)
    if support is not None:  # a row with an empty support draws from every bin
        inside = torch.where(support.any(-1, keepdim=True), support.to(w.dtype), inside)
    w = w * inside
    # a row with no weight: uniform over the support, not NaN
    w = torch.where(w.sum(-1, keepdim=True) > 0, w, inside)
    cumulative = torch.cat([torch.zeros_like(w[:, :1]), w.cumsum(-1)], -1)
    cdf = cumulative / cumulative[:, -1:]
    r, device = len(edges), edges.device
    if noise is None:
        u = torch.linspace(0.0, 1.0, n + 1, device=device).expand(r, n + 1).contiguous()
    else:
        u = (torch.arange(n + 1, device=device) + noise.rand(r, n + 1, device=device)) / (n + 1)
    return invert_cdf(edges, cdf, u)


def outer_weights(target: Tensor, source: Tensor, source_weights: Tensor) -> Tensor:
    """For each target interval (edges (R, N + 1)), the summed weight of every source interval
    (edges (R, M + 1), weights (R, M)) that overlaps it: the histogram's upper envelope on the
    target's intervals."""
    cumulative = torch.cat([torch.zeros_like(source_weights[:, :1]), source_weights.cumsum(-1)], -1)
    m = source_weights.shape[-1]
    first = (
        torch.searchsorted(source[:, :-1].contiguous(), target[:, :-1].contiguous(), right=True) - 1
    ).clamp(0, m - 1)
    last = torch.searchsorted(
        source[:, 1:].contiguous(), target[:, 1:].contiguous(), right=True
    ).clamp(0, m - 1)
    return cumulative[:, 1:].gather(-1, last) - cumulative[:, :-1].gather(-1, first)


def interlevel_loss(
    main_edges: Tensor,
    main_weights: Tensor,
    levels: list[tuple[Tensor, Tensor]],
    rows: Tensor | None = None,
) -> Tensor:
    """mip-NeRF 360's L_prop: each proposal level's histogram must bound the main weights (detached)
    from above; max(0, w - outer)^2 / w, averaged over intervals and summed over levels. `rows`
    (R,) bool: the rays the mean is over (the others' terms are left out; None: every ray)."""
    w = main_weights.detach().float()
    total = main_weights.new_zeros(())
    for edges, weights in levels:
        excess = (w - outer_weights(main_edges, edges, weights.float())).clamp(min=0)
        term = excess**2 / (w + EPS)
        if rows is None:
            total = total + term.mean()
        else:  # a mean over the chosen rows' intervals, with no read of how many there are
            kept = torch.where(rows[:, None], term, 0.0).sum()
            total = total + kept / (rows.sum() * term.shape[1]).clamp(min=1)
    return total


class UpdateSchedule:
    """When the proposals train (nerfacc's get_proposal_requires_grad_fn): every step at first, then
    at most every `every` steps, the gap growing linearly over `warmup` steps. On the other steps
    they run without gradient, so only the sampling costs. Its one counter is checkpointed with the
    run."""

    def __init__(self, every: int, warmup: int):
        self.every, self.warmup = every, warmup
        self.since_update = 0

    def due(self, step: int) -> bool:
        target = min(step / self.warmup, 1.0) * self.every if self.warmup else float(self.every)
        due = self.since_update >= target
        # counts this step: `every` apart at the end
        self.since_update = 1 if due else self.since_update + 1
        return due

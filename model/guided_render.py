"""LeCO's main-phase render (section 3.4): the occupancy network O picks the coarse bins of each hit ray, the
main Switch-NeRF renders samples in them in front of the background, and, while O learns, its keep/drop loss
(model/online_occupancy.py) and its placement loss (model/placement.py) come back with the render."""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from model.fields.background import BackgroundField
from model.fields.hmoe import OccupancyNetwork
from model.fields.switch_nerf import SwitchNeRF
from model.main_phase import MainRender, composite_field, cull_occluded, field_on_packed
from model.occupancy import OccupancyQuery
from model.occupancy_phase import render_background
from model.online_occupancy import OnlineOccupancy
from model.placement import placed_samples, placement_loss
from model.profiles import GuidedConfig, Profile
from model.rendering import Rendered, batched_weights
from model.samplers import PackedSamples, draw_guided, pack_edges, stratified_edges
from model.scenes.rays import RayBatch


def histogram(sigma: Tensor, edges: Tensor) -> Tensor:
    """(R, B) render weights of O's placement densities (R, B) over the coarse bins: where O expects the weight."""
    return batched_weights(sigma, edges[:, 1:] - edges[:, :-1])[0]


def confident_bins(keep: Tensor, weights: Tensor, min_share: float) -> Tensor:
    """The kept bins (R, B) holding at least `min_share` of their ray's kept histogram `weights` (R, B); a ray
    where none does keeps its heaviest kept bin, and a ray without any weight keeps them all, so every ray that
    had a bin still has one."""
    if min_share <= 0:
        return keep
    mass = weights * keep
    total = mass.sum(-1, keepdim=True)
    share = torch.where(total > 0, mass / total.clamp(min=1e-30), torch.ones_like(mass))  # no weight: keep all
    heaviest = torch.zeros_like(keep).scatter_(1, mass.argmax(-1, keepdim=True), True) & keep
    return (keep & (share >= min_share)) | heaviest


def placer(profile: Profile, query: OccupancyQuery, anneal: float,
           generator: torch.Generator | None) -> Callable[[Tensor, Tensor, Tensor], PackedSamples]:
    """draw_guided's `place`: `guided.main_samples` per ray over its kept bins, by O's annealed, padded histogram
    (the anneal's exponent 0 spreads them evenly over the kept bins, which are all one length)."""
    g = profile.guided

    def place(rows: Tensor, edges: Tensor, keep: Tensor) -> PackedSamples:
        if query.sigma is None:
            raise ValueError("guided.placement needs O's placement head: the HMoE is built with one when it is set")
        sigma = query.sigma.detach().reshape(-1, edges.shape[1] - 1, g.queries_per_bin).mean(dim=-1)[rows]
        weights = histogram(sigma, edges) ** anneal
        return placed_samples(edges, confident_bins(keep, weights, g.placement_min_share),
                              weights + g.placement_padding, g.main_samples, generator)

    return place


def render_guided(field: SwitchNeRF, background: BackgroundField, rays: RayBatch, profile: Profile,
                  query: OccupancyQuery, generator: torch.Generator | None, learner: OnlineOccupancy | None = None,
                  learn_placement: bool = False, anneal: float = 1.0) -> MainRender:
    """`query` asks O (with gradient while it learns this step); `learner`: O's keep/drop loss this step;
    `learn_placement`: O's placement loss this step; `anneal`: the exponent on O's histogram (nerfstudio's)."""
    g = profile.guided
    behind = render_background(background, rays, profile.background.samples, generator).rgb
    hit = torch.nonzero(rays.far > rays.near)[:, 0]
    sub = rays.subset(hit)  # only rays that cross the box have bins to keep
    with torch.no_grad():
        place = placer(profile, query, anneal, generator) if g.placement else None
        draw = draw_guided(sub.near, sub.far, sub.origins, sub.directions, query.occupied, g.coarse_samples,
                           g.split, generator, g.jitter, g.dilate, g.fallback, g.fallback_topk, query.scores, place,
                           g.queries_per_bin)
    local = draw.samples
    evaluated = 0
    if g.cull_transmittance is not None:
        evaluated = len(local)
        local = local.subset(cull_occluded(field, sub, local, g.cull_transmittance))
    samples = PackedSamples(local.starts, local.ends, hit[local.ray_index])
    out = field_on_packed(field, rays, samples)
    rendered = composite_field(out, rays, samples, behind)
    losses: list[Tensor] = []
    if learner is not None:
        losses.append(learner.loss(local, rendered.weights, sub, g.coarse_samples))
    if learn_placement and query.sigma is not None and len(sub):
        proposal = histogram(query.sigma.reshape(len(sub), g.coarse_samples, -1).mean(dim=-1), draw.edges)
        losses.append(g.placement_loss_weight * placement_loss(proposal, local, rendered.weights, sub.near, sub.far))
    stats = {"o_kept_ratio": float(draw.occupied_bins.float().mean()) if len(sub) else 0.0,
             "fallback_fraction": float(draw.lost.float().mean()) if len(sub) else 0.0}
    # Culled samples still ran the network once (without gradient), so they count, as vanilla's coarse ones do.
    return MainRender(rendered, out, (evaluated + len(samples)) / len(rays), None,
                      torch.stack(losses).sum() if losses else None, samples=samples, stats=stats)


def phase1_placement_loss(gate: OccupancyNetwork, rays: RayBatch, g: GuidedConfig,
                          generator: torch.Generator | None, rendered: Rendered, edges: Tensor) -> Tensor:
    """Phase 1's placement loss (guided.placement_in_phase1): O's histogram over the main phase's coarse bins,
    asked where the main phase will ask (jittered with `guided.jitter`), must bound the HMoE's detached render
    weights (`rendered` on `edges`) on the rays that cross the box, so the main phase starts with a head that
    already knows where the weight lies."""
    hit = torch.nonzero(rays.far > rays.near)[:, 0]
    sub = rays.subset(hit)
    coarse = stratified_edges(sub.near, sub.far, g.coarse_samples, None)
    u: Tensor | float = 0.5
    if g.jitter and generator is not None:
        u = torch.rand(coarse[:, 1:].shape, generator=generator, device=coarse.device, dtype=coarse.dtype)
    t = coarse[:, :-1] + (coarse[:, 1:] - coarse[:, :-1]) * u
    sigma = gate.query((sub.origins[:, None] + sub.directions[:, None] * t[..., None]).reshape(-1, 3))[1]
    if sigma is None:
        raise ValueError("guided.placement_in_phase1 needs O's placement head (guided.placement)")
    proposal = histogram(sigma.reshape(len(sub), -1), coarse)
    main = pack_edges(edges[hit])
    return g.placement_loss_weight * placement_loss(proposal, main, rendered.weights[hit].reshape(-1), sub.near,
                                                    sub.far)

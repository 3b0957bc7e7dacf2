"""LeCO's main-phase render (section 3.4): the occupancy network O picks the coarse bins of each hit
ray, the main Switch-NeRF renders samples in them in front of the background, and, while O learns,
its keep/drop loss (model/estimators/online.py) and its placement loss
(model/estimators/placement.py) come back with the render."""

from __future__ import annotations

from functools import partial

import torch
from torch import Tensor

from model.estimators.fine_placement import FineDraw, fine_placement_loss, fine_samples
from model.estimators.guided import BinOptions, draw_guided
from model.estimators.occupancy import OccupancyQuery
from model.estimators.online import OnlineOccupancy
from model.estimators.placement import (
    confident_bins,
    explored,
    placed_samples,
    placement_loss,
    subdivided,
    within_bin_shares,
)
from model.fields.background import BackgroundField
from model.fields.hmoe import OccupancyNetwork
from model.fields.switch_nerf import SwitchNeRF
from model.methods.leco.phase1 import render_background
from model.methods.main_phase import MainRender, composite_field, cull_occluded, field_on_packed
from model.methods.parts import Parts
from model.methods.stages import stage
from model.profiles import GuidedConfig, Profile
from model.render.noise import Noise
from model.render.samples import PackedSamples, pack_edges, stratified_edges
from model.render.volume import Rendered, batched_weights
from model.scenes.rays import RayBatch


def histogram(sigma: Tensor, edges: Tensor) -> Tensor:
    """(R, B) render weights of O's placement densities (R, B) over the coarse bins: where O expects
    the weight."""
    return batched_weights(sigma, edges[:, 1:] - edges[:, :-1])[0]


class Placer:
    """draw_guided's `place`: `guided.main_samples` per ray over its kept bins, by O's annealed,
    padded histogram (the anneal's exponent 0 spreads them evenly over the kept bins, which are all
    one length); with `guided.placement_fine`, in two passes
    (model/estimators/fine_placement.py), the last draw kept for its loss."""

    def __init__(
        self,
        profile: Profile,
        query: OccupancyQuery,
        rays: RayBatch,
        anneal: float,
        noise: Noise | None,
        learn: bool = False,
    ):
        """`learn`: O's placement learns this step, so the fine pass asks O with gradient (kept for
        the loss)."""
        self.g, self.query, self.rays, self.anneal, self.noise = (
            profile.guided,
            query,
            rays,
            anneal,
            noise,
        )
        self.learn = learn
        self.fine: FineDraw | None = None

    def __call__(self, rows: Tensor, edges: Tensor, keep: Tensor) -> PackedSamples:
        g, query = self.g, self.query
        if query.sigma is None:
            raise ValueError(
                "guided.placement needs O's placement head: the HMoE is built with one when it is "
                "set"
            )
        sigma = (
            query.sigma.detach()
            .reshape(-1, edges.shape[1] - 1, g.queries_per_bin)
            .mean(dim=-1)[rows]
        )
        weights = histogram(sigma, edges) ** self.anneal
        keep = confident_bins(keep, weights, g.placement_min_share)
        keep, mass = explored(keep, weights + g.placement_padding, edges, g.placement_explore)
        if not g.placement_fine:
            if g.placement_within != "uniform":
                shares = within_bin_shares(g.placement_within, mass, sigma, edges)
                edges, keep, mass = subdivided(edges, keep, mass, shares)
            return placed_samples(edges, keep, mass, g.main_samples, self.noise)
        density = lambda t: self.density(rows, t, grad=self.learn)  # noqa: E731
        samples, self.fine = fine_samples(
            rows,
            edges,
            keep,
            mass,
            g.placement_fine,
            g.main_samples,
            density,
            self.noise,
            self.anneal,
            g.placement_padding,
        )
        return samples

    def density(self, rows: Tensor, t: Tensor, grad: bool = True) -> Tensor:
        """O's placement density at depths t (R, M) along the given rows of the hit rays (`grad`:
        with gradient while O learns; placing needs none)."""
        points = self.rays.origins[rows, None] + self.rays.directions[rows, None] * t[..., None]
        return self.query.density(points.reshape(-1, 3), grad).reshape(t.shape)


def render_guided(
    field: SwitchNeRF,
    background: BackgroundField,
    rays: RayBatch,
    profile: Profile,
    query: OccupancyQuery,
    noise: Noise | None,
    learner: OnlineOccupancy | None = None,
    learn_placement: bool = False,
    anneal: float = 1.0,
) -> MainRender:
    """`query` asks O (with gradient while it learns this step); `learner`: O's keep/drop loss this
    step; `learn_placement`: O's placement loss this step; `anneal`: the exponent on O's histogram
    (nerfstudio's)."""
    g = profile.guided
    behind = render_background(background, rays, profile.background.samples, noise).rgb
    hit = torch.nonzero(rays.far > rays.near)[:, 0]
    sub = rays.subset(hit)  # only rays that cross the box have bins to keep
    with stage("sampler"), torch.no_grad():
        place = Placer(profile, query, sub, anneal, noise, learn_placement) if g.placement else None
        draw = draw_guided(
            sub.near,
            sub.far,
            sub.origins,
            sub.directions,
            query.occupied,
            noise,
            BinOptions.of(g),
            query.scores,
            place,
            all_hit=True,
        )
    local = draw.samples
    evaluated = 0
    if g.cull_transmittance is not None:
        evaluated = len(local)
        local = local.subset(cull_occluded(field, sub, local, g.cull_transmittance))
    samples = PackedSamples(local.starts, local.ends, hit[local.ray_index])
    out = field_on_packed(field, rays, samples)
    rendered = composite_field(out, rays, samples, behind)
    losses: list[Tensor] = []
    box_queries = 0
    with stage("losses"):  # O's, while it learns
        if learner is not None:
            rgb = rendered.rgb[hit] if learner.free_error > 0 else None  # only its free labels
            losses.append(learner.loss(local, rendered.weights, sub, g.coarse_samples, rgb))
            if learner.box_points:
                losses.append(learner.box_loss(partial(density_at, field), noise))
                box_queries = learner.box_points
        if learn_placement and query.sigma is not None and len(sub):
            proposal = histogram(
                query.sigma.reshape(len(sub), g.coarse_samples, -1).mean(dim=-1), draw.edges
            )
            losses.append(
                g.placement_loss_weight
                * placement_loss(proposal, local, rendered.weights, sub.near, sub.far)
            )
            if place is not None and place.fine is not None and len(place.fine.rows):
                fine = place.fine
                main = rendered.weights.reshape(len(fine.rows), g.main_samples)
                losses.append(g.placement_loss_weight * fine_placement_loss(fine, fine.sigma, main))
    stats: Parts = {
        "o_kept_ratio": draw.occupied_bins.float().mean() if len(sub) else 0.0,
        "fallback_fraction": draw.lost.float().mean() if len(sub) else 0.0,
    }
    # Culled samples and the box points O is taught at still ran the network once (without
    # gradient), so they count, as vanilla's coarse ones do.
    return MainRender(
        rendered,
        out,
        (evaluated + len(samples) + box_queries) / len(rays),
        None,
        torch.stack(losses).sum() if losses else None,
        samples=samples,
        stats=stats,
    )


def density_at(field: SwitchNeRF, points: Tensor) -> Tensor:
    """The main field's density at world points, as an occupancy grid's update asks it (no view
    direction, the first image's appearance, without the field's training noise)."""
    training = field.training
    field.eval()
    image = torch.zeros(len(points), dtype=torch.long, device=points.device)
    sigma = field(points, torch.zeros_like(points), image).sigma
    field.train(training)
    return sigma


def phase1_placement_loss(
    gate: OccupancyNetwork,
    rays: RayBatch,
    g: GuidedConfig,
    noise: Noise | None,
    rendered: Rendered,
    edges: Tensor,
) -> Tensor:
    """Phase 1's placement loss (guided.placement_in_phase1): O's histogram over the main phase's
    coarse bins, asked where the main phase will ask (jittered with `guided.jitter`), must bound the
    HMoE's detached render weights (`rendered` on `edges`) on the rays that cross the box, so the
    main phase starts with a head that already knows where the weight lies."""
    hit = torch.nonzero(rays.far > rays.near)[:, 0]
    sub = rays.subset(hit)
    coarse = stratified_edges(sub.near, sub.far, g.coarse_samples, None)
    u: Tensor | float = 0.5
    if g.jitter and noise is not None:
        u = noise.rand(*coarse[:, 1:].shape, device=coarse.device, dtype=coarse.dtype)
    t = coarse[:, :-1] + (coarse[:, 1:] - coarse[:, :-1]) * u
    sigma = gate.query(
        (sub.origins[:, None] + sub.directions[:, None] * t[..., None]).reshape(-1, 3)
    )[1]
    if sigma is None:
        raise ValueError("guided.placement_in_phase1 needs O's placement head (guided.placement)")
    proposal = histogram(sigma.reshape(len(sub), -1), coarse)
    main = pack_edges(edges[hit])
    return g.placement_loss_weight * placement_loss(
        proposal, main, rendered.weights[hit].reshape(-1), sub.near, sub.far
    )

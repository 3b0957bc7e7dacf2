"""LeCO+Prop (`leco-prop`): LeCO decides where not to look, proposal networks decide where to look.

Phase 1 trains the HMoE with the paper's losses, as `leco` does (section 3.3). In the main phase O
keeps or drops each coarse bin of a hit ray (threshold, dilation, top-k fallback and online learning
as LeCO's, model/estimators/guided.py), and two proposal levels, trained with mip-NeRF 360's
interlevel loss as in `prop`, place the main samples on the axis O's keep bounds
(`leco_prop.bound`, model/estimators/kept_axis.py). A keep/drop over fixed bins is a good mask and a
poor pdf; the proposals are a good pdf that spends most of its first level on empty space. The main
network starts from phase 1's experts (LeCO's warm start)."""

from __future__ import annotations

from functools import partial

import torch
from torch import Tensor, nn

from model.estimators.guided import BinOptions, keep_bins
from model.estimators.kept_axis import Axis, KeptAxis, bounded
from model.estimators.occupancy import OccupancyQuery
from model.estimators.online import OnlineOccupancy
from model.estimators.proposal import interlevel_loss
from model.methods.base import Networks, Step, SweepPoint
from model.methods.leco.guided_render import density_at, phase1_placement_loss
from model.methods.leco.method import LeCOMethod
from model.methods.leco.phase1 import occupancy_step
from model.methods.main_phase import MainRender
from model.methods.parts import Parts
from model.methods.prop import ProposalMethod
from model.methods.stages import stage
from model.render.noise import Noise
from model.render.samples import PackedSamples
from model.render.volume import Rendered, batched_weights
from model.scenes.rays import RayBatch


class LeCOPropMethod(LeCOMethod, ProposalMethod):
    """LeCO's phase 1, O and warm start (LeCOMethod) with S+Prop's proposal levels
    (ProposalMethod): each inherited piece is the one its owner has, and the main step is here."""

    def build(self, num_images: int, aabb: Tensor) -> Networks:
        models = LeCOMethod.build(self, num_images, aabb)
        models.proposals = self.proposal_networks()
        self.aabb = aabb.float()
        return models

    def sweep(self) -> list[SweepPoint]:
        return ProposalMethod.sweep(self)  # the proposals place a fixed budget per hit ray

    def step(self, models: Networks, step: Step) -> tuple[Tensor, dict]:
        if step.phase == "occupancy":
            if not self.profile.leco_prop.prop_in_phase1:
                return LeCOMethod.step(self, models, step)
            warm = partial(self.phase1_sampler_loss, models, step)
            return occupancy_step(
                models.hmoe,
                models.occupancy_background,
                step.rays,
                self.profile.occupancy,
                self.profile.background.samples,
                step.noise,
                step.progress,
                ("interlevel_loss", warm),
            )
        learn = self.schedule.due(step.phase_step)
        render, levels, edges = self.draw(models, step.rays, step.noise, step.phase_step, learn)
        with stage("losses"):
            return self.loss_with_proposals(render, step.rays, levels, edges, learn)

    def render_main(
        self,
        models: Networks,
        rays: RayBatch,
        noise: Noise | None,
        phase_step: int | None,
    ) -> MainRender:
        return self.draw(models, rays, noise, phase_step, learn=False)[0]

    def draw(
        self,
        models: Networks,
        rays: RayBatch,
        noise: Noise | None,
        phase_step: int | None,
        learn: bool,
    ) -> tuple[MainRender, list[tuple[Tensor, Tensor]], Tensor]:
        """The main render on the axis O bounds, the proposal levels (with gradient when `learn`)
        and the main samples' edges on that axis; O's keep/drop loss comes back with the render
        while O learns (model/estimators/online.py)."""
        g, bound = self.profile.guided, self.profile.leco_prop.bound
        hits = self.hits(rays)
        sub = rays.subset(hits)
        axis: Axis | None = None
        first: tuple[Tensor, Tensor, Tensor] | None = None
        learner: OnlineOccupancy | None = None
        stats: Parts = {}
        if bound != "off":  # the control arm asks O nothing
            query = self.main_query()
            keeps = phase_step is not None and g.online_learns(phase_step)
            # in the level form O's histogram is a proposal level: it learns when they do
            query.learn = keeps or (learn and bound == "level")
            learner = query if keeps and isinstance(query, OnlineOccupancy) else None
            with stage("sampler"), torch.no_grad():
                bins = keep_bins(
                    sub.near,
                    sub.far,
                    sub.origins,
                    sub.directions,
                    query.occupied,
                    noise,
                    BinOptions.of(g),
                    query.scores,
                    all_hit=True,
                )
            explore = self.profile.leco_prop.explore
            support = bounded(bins.keep, "mask" if bound == "level" else bound)
            axis = kept = KeptAxis.of(bins.edges, support, explore)
            if bound == "level":  # O's placement histogram over its kept bins: the first level
                first = (kept.s_edges, self.o_histogram(query, kept), kept.s_edges.diff() > 0)
            if len(sub):
                share = kept.length() / (sub.far - sub.near)
                stats = {
                    "o_kept_ratio": bins.occupied_bins.float().mean(),
                    "fallback_fraction": bins.lost.float().mean(),
                    "bounded_length": share.mean(),
                }
        with stage("sampler"), torch.set_grad_enabled(learn):
            levels, edges = self.propose(models, sub, noise, phase_step, axis, first)
        render = self.render_on(models, rays, hits, edges, noise, axis)
        render.stats.update(stats)
        if learner is not None and render.samples is not None:
            local = render.samples
            order = torch.arange(len(sub), device=hits.device)
            local = PackedSamples(
                local.starts, local.ends, order.repeat_interleave(edges.shape[1] - 1)
            )
            weights = render.rendered.weights.reshape(-1)
            with stage("losses"):
                rgb = render.rendered.rgb[hits] if learner.free_error > 0 else None
                render.occupancy_loss = learner.loss(local, weights, sub, g.coarse_samples, rgb)
                if learner.box_points:  # charged as main samples, as culled ones are
                    render.occupancy_loss = render.occupancy_loss + learner.box_loss(
                        partial(density_at, models.field), noise
                    )
                    render.samples_per_ray += learner.box_points / len(rays)
        return render, levels, edges

    def o_histogram(self, query: OccupancyQuery, axis: KeptAxis) -> Tensor:
        """(R, B) the render weights of O's placement densities over the coarse bins on the kept
        axis (a dropped bin is zero long there, so it holds none), with gradient while O learns."""
        if query.sigma is None:
            raise ValueError("leco_prop.bound=level needs O's placement head (guided.placement)")
        b = axis.keep.shape[1]
        sigma = query.sigma.reshape(len(axis.keep), b, -1).mean(dim=-1)
        return batched_weights(sigma, axis.s_edges.diff())[0]

    def phase1_sampler_loss(
        self, models: Networks, step: Step, rendered: Rendered, edges: Tensor
    ) -> Tensor:
        """`leco_prop.prop_in_phase1`: the proposals over each hit ray's whole segment must bound
        the HMoE's detached render weights (`rendered` on `edges`, mip-NeRF 360's eq. 13); with O's
        placement head (the level form), its histogram must too (LeCO's phase-1 placement loss)."""
        hits = self.hits(step.rays)
        levels, _ = self.propose(models, step.rays.subset(hits), step.noise, step.phase_step)
        loss = self.profile.prop.loss_weight * interlevel_loss(
            edges[hits], rendered.weights[hits], levels
        )
        g = self.profile.guided
        if g.placement and g.placement_in_phase1:
            gate = models.hmoe.gate
            loss = loss + phase1_placement_loss(gate, step.rays, g, step.noise, rendered, edges)
        return loss

    def trained_modules(self, models: Networks, phase: str) -> list[nn.Module]:
        if phase == "occupancy":
            warm = [models.proposals] if self.profile.leco_prop.prop_in_phase1 else []
            return LeCOMethod.trained_modules(self, models, phase) + warm
        return ProposalMethod.trained_modules(self, models, phase)

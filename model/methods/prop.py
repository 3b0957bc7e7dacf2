"""S+Prop: Switch-NeRF's foreground sampled by proposal networks (mip-NeRF 360 / nerfacto /
nerfacc's PropNetEstimator) instead of its coarse + fine passes: the strongest learned sampler, as a
baseline.

Sizes: the proposal levels together have as many parameters as LeCO's occupancy network O at the
same profile (13,888 against O's 13,962 at `cpu`, 153,760 against 153,865 at `paper`), and the main
network takes `prop.main_samples` per hit ray, LeCO's own count, so the two learned samplers are
compared at equal size and equal main-network work (for the hash field O places `ngp.main_samples`,
twice that at `cpu`, which measured better for it and worse for the proposals). Every proposal
forward and backward runs inside the training step, so it is charged to training time. Its
occupancy, for the paper's Table 1, is the last proposal level's density thresholded by the
occupancy grid's own rule (one full update of a grid at `grid.resolution`)."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor, nn

from model.estimators.grid import GridEstimator
from model.estimators.kept_axis import Axis, SegmentAxis
from model.estimators.proposal import UpdateSchedule, anneal_power, interlevel_loss, pdf_edges
from model.fields.output import FieldOutput
from model.fields.proposal import ProposalDensity
from model.methods.base import Method, Networks, Occupied, Step, SweepPoint, mean_of
from model.methods.costs import proposal_parameters, proposal_width
from model.methods.leco.phase1 import render_background
from model.methods.main_phase import MainRender, grid_step_size, main_loss, render_batched
from model.methods.parts import Parts
from model.methods.stages import stage
from model.profiles import Profile
from model.render.noise import Noise
from model.render.samples import PackedSamples, pack_edges, stratified_edges
from model.render.volume import Rendered, batched_weights, composite_batched
from model.scenes.rays import RayBatch


def render_on_axis(
    field: nn.Module, rays: RayBatch, axis: Axis, edges: Tensor, behind: Tensor
) -> tuple[Rendered, FieldOutput, PackedSamples]:
    """`render_batched` for intervals on an axis other than the ray's segment: each interval is a
    sample at t(mid) with its length on the axis as delta (model/estimators/kept_axis.py); also the
    samples, packed, as [t - delta / 2, t + delta / 2]."""
    mids, deltas = 0.5 * (edges[:, 1:] + edges[:, :-1]), edges[:, 1:] - edges[:, :-1]
    t = axis.to_t(mids)
    r, n = t.shape
    with stage("field"):
        xyz = rays.origins[:, None] + rays.directions[:, None] * t[..., None]
        out = field(
            xyz.reshape(-1, 3),
            rays.directions.repeat_interleave(n, 0),
            rays.image_index.repeat_interleave(n, 0),
        )
    rendered = composite_batched(
        out.sigma.reshape(r, n), out.rgb.reshape(r, n, 3), t, deltas, behind
    )
    ray = torch.arange(r, device=t.device).repeat_interleave(n)
    t, half = t.reshape(-1), 0.5 * deltas.reshape(-1)
    return rendered, out, PackedSamples(t - half, t + half, ray)


def scatter(values: Tensor, index: Tensor, size: int, fill: float) -> Tensor:
    """(size,) filled with `fill`, `values` at `index`."""
    return torch.full((size,), fill, dtype=values.dtype, device=values.device).index_copy(
        0, index, values
    )


class ProposalMethod(Method):
    def __init__(self, profile: Profile):
        super().__init__(profile)
        self.schedule = UpdateSchedule(profile.prop.update_every, profile.prop.update_warmup)

    aabb: Tensor  # the foreground box, set by build()

    def build(self, num_images: int, aabb: Tensor) -> Networks:
        models = super().build(num_images, aabb)
        models.proposals = self.proposal_networks()
        self.aabb = aabb.float()
        return models

    def proposal_networks(self) -> nn.ModuleList:
        """One density MLP per proposal level (`prop.samples`)."""
        p, width = self.profile.prop, proposal_width(self.profile)
        return nn.ModuleList(
            ProposalDensity(width, p.layers, self.profile.network.xyz_frequencies)
            for _ in p.samples
        )

    def components(self, num_images: int) -> dict[str, int]:
        return {
            "proposal_networks": proposal_parameters(self.profile),
            **super().components(num_images),
        }

    def sweep(self) -> list[SweepPoint]:
        p = self.profile.prop
        return [
            SweepPoint(tag, f"{n} main samples", {"prop.main_samples": n})
            for tag, n in (("lean", max(p.main_samples // 2, 1)), ("rich", 2 * p.main_samples))
        ]

    # ----- a run
    # --------------------------------------------------------------------------------------
    def trained_modules(self, models: Networks, phase: str) -> list[nn.Module]:
        return [models.field, models.background, models.proposals]

    def to(self, device: torch.device) -> "ProposalMethod":
        self.aabb = self.aabb.to(device)
        return self

    def step(self, models: Networks, step: Step) -> tuple[Tensor, dict]:
        learn = self.schedule.due(step.phase_step)
        with stage("sampler"):
            hits = self.hits(step.rays, self.profile.prop.static_shapes)
            with torch.set_grad_enabled(learn):
                levels, edges = self.propose(
                    models, step.rays.subset(hits), step.noise, step.phase_step
                )
        render = self.render_on(models, step.rays, hits, edges, step.noise)
        with stage("losses"):
            return self.loss_with_proposals(render, step.rays, levels, edges, learn)

    def loss_with_proposals(
        self,
        render: MainRender,
        rays: RayBatch,
        levels: list[tuple[Tensor, Tensor]],
        edges: Tensor,
        learn: bool,
    ) -> tuple[Tensor, Parts]:
        """The main loss, plus the interlevel loss on a step the proposals learn (`levels` and the
        main `edges` of the hit rays, as `propose` returns them)."""
        loss, parts = main_loss(
            render,
            rays,
            self.profile.balance_weight,
            self.profile.guided.coarse_samples,
            self.distortion_weight(),
        )
        hits = len(edges)
        parts["proposal_samples_per_ray"] = (
            float(sum(self.profile.prop.samples)) * hits / max(len(rays), 1)
        )
        # only the proposals get this gradient: the main weights are detached inside
        if learn and hits:
            # with static shapes the misses' rows are in `edges`, empty: the mean is the hit rays'
            rows = rays.far > rays.near if self.profile.prop.static_shapes else None
            l_prop = interlevel_loss(edges, render.rendered.weights, levels, rows)
            loss = loss + self.profile.prop.loss_weight * l_prop
            parts["interlevel_loss"] = l_prop.detach()
            parts["loss"] = loss.detach()
        return loss, parts

    @staticmethod
    def hits(rays: RayBatch, static_shapes: bool = False) -> Tensor:
        """Indices of the rays that cross the foreground box: the others have no segment to sample,
        so neither the proposals nor the main network see them (they render the background alone, as
        LeCO's do). With `static_shapes` every ray, read from nothing: a miss's segment is empty
        (near = far = 0, model/scenes/bounds.py ray_aabb), so its intervals have zero length and
        zero weight and it renders its background alone all the same."""
        if static_shapes:
            return torch.arange(len(rays), device=rays.far.device)
        return torch.nonzero(rays.far > rays.near)[:, 0]

    def propose(
        self,
        models: Networks,
        rays: RayBatch,
        noise: Noise | None,
        phase_step: int | None,
        axis: Axis | None = None,
        first: tuple[Tensor, Tensor, Tensor] | None = None,
    ) -> tuple[list[tuple[Tensor, Tensor]], Tensor]:
        """Each proposal level's (edges, weights) and the main network's edges (R, main_samples +
        1), all on `axis` (model/estimators/kept_axis.py; default: each ray's [near, far]).
        `first`: a level given in place of stratified samples, (edges, weights, support), which the
        first network's samples are drawn from (LeCO+Prop's `level` form: O's histogram)."""
        p = self.profile.prop
        axis = axis if axis is not None else SegmentAxis(rays.near, rays.far)
        anneal = anneal_power(phase_step, p.anneal_steps, p.anneal_slope)
        levels = []
        if first is None:
            edges = stratified_edges(axis.start, axis.end, p.samples[0], noise)
        else:
            given, weights, support = first
            levels.append((given, weights))
            edges = pdf_edges(
                given, weights, p.samples[0], noise, anneal, p.histogram_padding, support
            )
        for i, network in enumerate(models.proposals):
            mids, deltas = 0.5 * (edges[:, 1:] + edges[:, :-1]), edges[:, 1:] - edges[:, :-1]
            t = axis.to_t(mids)
            xyz = rays.origins[:, None] + rays.directions[:, None] * t[..., None]
            sigma = network(xyz.reshape(-1, 3)).reshape(mids.shape)
            weights = batched_weights(sigma, deltas)[0]
            levels.append((edges, weights))
            n = p.samples[i + 1] if i + 1 < len(p.samples) else p.main_samples
            edges = pdf_edges(edges, weights, n, noise, anneal, p.histogram_padding)
        return levels, edges.detach()

    def render_on(
        self,
        models: Networks,
        rays: RayBatch,
        hits: Tensor,
        edges: Tensor,
        noise: Noise | None,
        axis: Axis | None = None,
    ) -> MainRender:
        """The main network on the hit rays' intervals (`edges` on `axis`, one row per hit ray,
        batched as the proposals draw them), composited in front of the background of every ray; a
        ray that misses the box shows its background. `rendered.weights` is (hit rays,
        main_samples)."""
        behind = render_background(
            models.background, rays, self.profile.background.samples, noise
        ).rgb
        if axis is None:
            sub, out = render_batched(models.field, rays.subset(hits), edges, behind[hits])
            packed = pack_edges(edges)
        else:
            sub, out, packed = render_on_axis(
                models.field, rays.subset(hits), axis, edges, behind[hits]
            )
        rendered = Rendered(
            behind.index_copy(0, hits, sub.rgb),
            scatter(sub.depth, hits, len(rays), 0.0),
            scatter(sub.opacity, hits, len(rays), 0.0),
            sub.weights,
            scatter(sub.transmittance, hits, len(rays), 1.0),
        )
        samples = PackedSamples(packed.starts, packed.ends, hits[packed.ray_index])
        return MainRender(rendered, out, len(samples) / max(len(rays), 1), None, samples=samples)

    def render_main(
        self,
        models: Networks,
        rays: RayBatch,
        noise: Noise | None,
        phase_step: int | None,
    ) -> MainRender:
        hits = self.hits(rays, self.profile.prop.static_shapes)
        with torch.no_grad():
            _, edges = self.propose(models, rays.subset(hits), noise, phase_step)
        return self.render_on(models, rays, hits, edges, noise)

    def proposal_grid(self, models: Networks) -> GridEstimator:
        """The last proposal level's density through one full update of an occupancy grid: the
        grid's rule."""
        g, network = self.profile.grid, models.proposals[-1]
        grid = GridEstimator(self.aabb, g.resolution).to(next(network.parameters()).device)
        was = network.training
        network.eval()
        grid.update(
            0,
            network,
            grid_step_size(grid, g.march_steps),
            g.threshold,
            g.decay,
            warmup_steps=1,
            every=1,
            generator=torch.Generator().manual_seed(0),
        )
        network.train(was)
        return grid

    def occupancy(self, models: Networks, phase: str) -> Occupied | None:
        return self.proposal_grid(models).occupied

    def final_occupancy(self, models: Networks) -> Occupied | None:
        return self.proposal_grid(models).occupied

    def state_dict(self) -> dict | None:
        return {"since_update": self.schedule.since_update}

    def load_state_dict(self, state: dict | None) -> None:
        if state is not None:
            self.schedule.since_update = state["since_update"]

    def summary_occupancy(self, final: Path, main: list[dict], first: list[dict]) -> dict:
        return {
            "params": proposal_parameters(self.profile),
            "occupancy_ratio": mean_of(main, "occupancy_ratio"),
        }

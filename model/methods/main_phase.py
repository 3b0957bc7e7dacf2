"""The main Switch-NeRF network's step under each sampler (paper section 3.4 and the baselines):

- `vanilla`: stratified coarse + inverse-CDF fine through the same network, all composited together;
- `guided` (LeCO): coarse bins -> the occupancy network O -> kept bins split or placed
  (model/methods/leco/guided_render.py);
- `grid`: nerfacc-style marching through the occupancy grid (the grid itself is updated by the
  caller).

Every sampler renders the background behind the foreground, so the three differ only in which
foreground points the main network sees. Loss = L_r + balance_weight * balance loss (Switch-NeRF,
5e-4)."""

from __future__ import annotations

from dataclasses import dataclass
from dataclasses import field as dataclass_field

import torch
from torch import Tensor

from model.estimators.grid import GridEstimator
from model.fields.background import BackgroundField, background_samples
from model.fields.output import FieldOutput
from model.fields.switch_nerf import SwitchNeRF
from model.methods.leco.phase1 import field_on_edges, render_background
from model.methods.parts import Parts, psnr
from model.methods.stages import stage
from model.profiles import Profile
from model.render.accounting import step_accounting
from model.render.front_to_back import front_to_back
from model.render.losses import (
    balance_loss,
    dispatch_fractions,
    distortion_loss,
    rendering_loss,
)
from model.render.noise import Noise
from model.render.samples import (
    PackedSamples,
    inverse_cdf_edges,
    merge_edges,
    pack_edges,
    stratified_edges,
)
from model.render.volume import Rendered, composite_batched, composite_packed, packed_transmittance
from model.scenes.rays import RayBatch


@dataclass
class MainRender:
    rendered: Rendered
    out: FieldOutput | None  # None when no ray had a foreground sample
    samples_per_ray: float  # main-network samples per ray (the cost the samplers compete on)
    # kept fraction of coarse samples (guided) or of march steps (grid)
    occupancy_ratio: float | Tensor | None
    occupancy_loss: Tensor | None = None  # O's own loss when it keeps learning (guided.online)
    # The main network's samples, packed (zero-length intervals of a batched sampler included: they
    # cost too); model/render/accounting.py counts what reached the main network from them. None:
    # not known.
    samples: PackedSamples | None = None
    # a sampler's own figures, logged as they are (tensors are read on logging steps only)
    stats: Parts = dataclass_field(default_factory=dict)


def field_on_packed(
    field: SwitchNeRF, rays: RayBatch, samples: PackedSamples
) -> FieldOutput | None:
    if len(samples) == 0:
        return None
    with stage("field"):
        i = samples.ray_index
        xyz = rays.origins[i] + rays.directions[i] * samples.mids[:, None]
        return field(xyz, rays.directions[i], rays.image_index[i])


def field_on_packed_at(
    field: SwitchNeRF, rays: RayBatch, samples: PackedSamples, index: Tensor
) -> FieldOutput:
    """The field at the packed samples `index` picks."""
    i, mids = samples.ray_index[index], samples.mids[index]
    return field(
        rays.origins[i] + rays.directions[i] * mids[:, None],
        rays.directions[i],
        rays.image_index[i],
    )


def composite_field(
    out: FieldOutput | None, rays: RayBatch, samples: PackedSamples, behind: Tensor
) -> Rendered:
    r = len(rays)
    if out is None:  # every ray is background only
        empty = torch.zeros(0, device=behind.device)
        return composite_packed(
            empty,
            torch.zeros(0, 3, device=behind.device),
            empty,
            empty,
            torch.zeros(0, dtype=torch.long, device=behind.device),
            r,
            behind,
        )
    return composite_packed(
        out.sigma, out.rgb, samples.mids, samples.deltas, samples.ray_index, r, behind
    )


def render_batched(
    field, rays: RayBatch, edges: Tensor, behind: Tensor
) -> tuple[Rendered, FieldOutput]:
    out, mids, deltas = field_on_edges(field, rays, edges)
    r, n = deltas.shape
    return composite_batched(
        out.sigma.reshape(r, n), out.rgb.reshape(r, n, 3), mids, deltas, behind
    ), out


def render_vanilla(
    field: SwitchNeRF,
    background: BackgroundField,
    rays: RayBatch,
    profile: Profile,
    noise: Noise | None,
) -> MainRender:
    cfg = profile.vanilla
    behind = render_background(background, rays, profile.background.samples, noise).rgb
    with stage("sampler"):
        coarse = stratified_edges(rays.near, rays.far, cfg.coarse_samples, noise)
    if cfg.fine_samples == 0:
        rendered, out = render_batched(field, rays, coarse, behind)
        return MainRender(
            rendered, out, float(cfg.coarse_samples), None, samples=pack_edges(coarse)
        )
    with torch.no_grad():  # coarse weights only place the fine samples
        weights = render_batched(field, rays, coarse, behind)[0].weights
    with stage("sampler"):
        edges = merge_edges(coarse, inverse_cdf_edges(coarse, weights, cfg.fine_samples, noise))
    rendered, out = render_batched(field, rays, edges, behind)
    # Coarse points run the network twice (once without gradient to place the fine ones).
    return MainRender(
        rendered,
        out,
        float(cfg.coarse_samples + edges.shape[1] - 1),
        None,
        samples=pack_edges(edges),
    )


def cull_occluded(field: SwitchNeRF, rays: RayBatch, samples: PackedSamples, eps: float) -> Tensor:
    """nerfacc's early stop for a learned sampler: one gradient-free pass of the main field finds
    the samples its current density already hides (T_i < eps), so the pass with gradient runs on the
    visible ones only. Returns the mask of the samples to keep."""
    if len(samples) == 0:
        return torch.ones(0, dtype=torch.bool, device=rays.near.device)
    with torch.no_grad():
        out = field_on_packed(field, rays, samples)
        assert out is not None  # there are samples (checked above)
        reach = packed_transmittance(out.sigma, samples.deltas, samples.ray_index, len(rays))
    return reach >= eps


def grid_step_size(grid: GridEstimator, march_steps: int) -> float:
    """nerfacc's render_step_size: the box diagonal over the number of marching steps."""
    return grid.diagonal / march_steps


def render_background_cascaded(
    background: BackgroundField,
    rays: RayBatch,
    samples: int,
    grid: GridEstimator,
    noise: Noise | None,
) -> tuple[Tensor, Tensor]:
    """The background's colour with its samples culled by the grid's outer cascades (Instant-NGP
    skips empty space beyond the box too): a sample in a free cell is dropped, one beyond the
    outermost level is kept. A dropped sample had no density, so compositing the kept ones with
    their own intervals is the same integral. Returns the colour and the kept share."""
    t, deltas = background_samples(rays.far, samples, noise, background.sky_at_infinity)
    xyz = rays.origins[:, None, :] + rays.directions[:, None, :] * t[..., None]
    flat = xyz.reshape(-1, 3)
    with torch.no_grad():
        keep = grid.not_free(flat)
        # the kept samples' indices once (one wait on CUDA), not once for each tensor masked
        kept = torch.nonzero(keep)[:, 0]
    ray = kept // samples  # sample i of the flat (R, samples) layout belongs to ray i // samples
    sigma, rgb = background(flat[kept], rays.directions[ray], rays.image_index[ray])
    t_kept, deltas_kept = t.reshape(-1)[kept], deltas.reshape(-1)[kept]
    rendered = composite_packed(sigma, rgb, t_kept, deltas_kept, ray, len(rays), sigma.new_zeros(3))
    return rendered.rgb, keep.float().mean() if len(keep) else rendered.rgb.new_zeros(())


def render_grid(
    field: SwitchNeRF,
    background: BackgroundField,
    rays: RayBatch,
    background_samples_per_ray: int,
    march_steps: int,
    grid: GridEstimator,
    noise: Noise | None,
    early_stop_eps: float = 0.0,
) -> MainRender:
    """`early_stop_eps` > 0: rays stop at that transmittance (model/render/front_to_back.py),
    for image renders; the samples reported are then the ones that ran."""
    stats: Parts = {}
    if grid.levels > 1:
        with stage("background"):
            behind, stats["background_kept"] = render_background_cascaded(
                background, rays, background_samples_per_ray, grid, noise
            )
    else:
        behind = render_background(background, rays, background_samples_per_ray, noise).rgb
    step = grid_step_size(grid, march_steps)
    with stage("sampler"):
        samples = grid.sample(
            rays.origins, rays.directions, rays.near, rays.far, step, noise, grid.diagonal
        )
    possible = ((rays.far - rays.near) / step).ceil().clamp(min=0).sum()
    if early_stop_eps > 0:
        out, samples = front_to_back(
            lambda i: field_on_packed_at(field, rays, samples, i),
            samples,
            len(rays),
            early_stop_eps,
        )
    else:  # training: every sample in one pass, no index gathers
        out = field_on_packed(field, rays, samples)
    return MainRender(
        composite_field(out, rays, samples, behind),
        out,
        len(samples) / len(rays),
        possible.new_full((), len(samples)) / possible.clamp(min=1.0),
        samples=samples,
        stats=stats,
    )


def main_loss(
    render: MainRender,
    rays: RayBatch,
    balance_weight: float,
    bins: int | None = None,
    distortion_weight: float = 0.0,
) -> tuple[Tensor, Parts]:
    """L_r + balance_weight * balance loss (+ distortion_weight * L_dist), and the parts as
    detached tensors (model/methods/parts.py: read on the steps the loop logs); with `bins`, what
    reached the main network counted on that many coarse bins per hit ray
    (model/render/accounting.py), the same way for every method."""
    l_r = rendering_loss(render.rendered.rgb, rays.rgb)
    loss = l_r
    parts: Parts = {
        "rendering_loss": l_r.detach(),
        "samples_per_ray": render.samples_per_ray,
        **render.stats,
    }
    weights = render.rendered.weights.reshape(-1)
    if distortion_weight > 0 and render.samples is not None:
        # a sampler's weights are per sample of `samples`, packed or batched in the same order
        assert len(weights) == len(render.samples), "weights and samples disagree"
        l_dist = distortion_loss(weights, render.samples, rays.near, rays.far, len(rays))
        loss = loss + distortion_weight * l_dist
        parts["distortion_loss"] = l_dist.detach()
    if bins is not None and render.samples is not None:
        parts.update(step_accounting(render.samples, rays.near, rays.far, bins))
    if render.out is not None:
        l_b = balance_loss(render.out.gate_probs, render.out.expert)
        loss = loss + balance_weight * l_b
        parts["balance_loss"] = l_b.detach()
        fractions, _ = dispatch_fractions(render.out.gate_probs.detach(), render.out.expert)
        parts.update({f"fraction_expert_{i}": f for i, f in enumerate(fractions)})
    if render.occupancy_ratio is not None and "occupancy_ratio" not in parts:
        parts["occupancy_ratio"] = render.occupancy_ratio
    if render.occupancy_loss is not None:  # only O's parameters get its gradient
        loss = loss + render.occupancy_loss
        parts["occupancy_online_loss"] = render.occupancy_loss.detach()
    parts["loss"] = loss.detach()
    parts["psnr"] = psnr(l_r)
    return loss, parts

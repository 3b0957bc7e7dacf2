"""One step of LeCO's occupancy phase (paper section 3.3): stratified samples in each ray's
foreground segment through the HMoE, the background behind them, and L_f = w_r L_r + w_g L_g + w_d
L_d."""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from model.fields.background import BackgroundField, background_samples
from model.fields.hmoe import HMoE
from model.fields.output import FieldOutput
from model.methods.parts import Parts, psnr
from model.methods.schedules import log_linear
from model.methods.stages import stage
from model.profiles import OccupancyPhaseConfig
from model.render.losses import (
    density_loss,
    gate_statistics,
    imbalanced_gate_loss,
    rendering_loss,
    visibility_loss,
)
from model.render.noise import Noise
from model.render.samples import stratified_edges
from model.render.volume import Rendered, composite_batched
from model.scenes.rays import RayBatch


def render_background(
    background: BackgroundField, rays: RayBatch, samples: int, noise: Noise | None
) -> Rendered:
    with stage("background"):
        t, deltas = background_samples(rays.far, samples, noise, background.sky_at_infinity)
        xyz = rays.origins[:, None, :] + rays.directions[:, None, :] * t[..., None]
        r = len(rays)
        sigma, rgb = background(
            xyz.reshape(-1, 3),
            rays.directions.repeat_interleave(samples, 0),
            rays.image_index.repeat_interleave(samples, 0),
        )
        return composite_batched(
            sigma.reshape(r, samples), rgb.reshape(r, samples, 3), t, deltas, sigma.new_zeros(3)
        )


def field_on_edges(field, rays: RayBatch, edges: Tensor) -> tuple[FieldOutput, Tensor, Tensor]:
    """A field (HMoE or Switch-NeRF) on every interval of (R, N + 1) edges: output, mids and deltas
    (R, N)."""
    n = edges.shape[1] - 1
    mids, deltas = 0.5 * (edges[:, 1:] + edges[:, :-1]), edges[:, 1:] - edges[:, :-1]
    with stage("field"):
        xyz = rays.origins[:, None] + rays.directions[:, None] * mids[..., None]
        out = field(
            xyz.reshape(-1, 3),
            rays.directions.repeat_interleave(n, 0),
            rays.image_index.repeat_interleave(n, 0),
        )
    return out, mids, deltas


def render_hmoe(
    model: HMoE,
    background: BackgroundField,
    rays: RayBatch,
    samples: int,
    background_samples_per_ray: int,
    noise: Noise | None,
) -> tuple[Rendered, FieldOutput, Tensor]:
    """The HMoE's image of a batch of rays (stratified samples), its field output and the sample
    edges."""
    r = len(rays)
    edges = stratified_edges(rays.near, rays.far, samples, noise)
    out, mids, deltas = field_on_edges(model, rays, edges)
    behind = render_background(background, rays, background_samples_per_ray, noise)
    rendered = composite_batched(
        out.sigma.reshape(r, samples), out.rgb.reshape(r, samples, 3), mids, deltas, behind.rgb
    )
    return rendered, out, edges


# A loss on phase 1's render besides L_f (O's placement head learning the HMoE's weights): render,
# edges -> loss
ExtraLoss = Callable[[Rendered, Tensor], Tensor]


def occupancy_step(
    model: HMoE,
    background: BackgroundField,
    rays: RayBatch,
    cfg: OccupancyPhaseConfig,
    background_samples_per_ray: int,
    noise: Noise | None,
    progress: float = 0.0,
    extra: tuple[str, ExtraLoss] | None = None,
) -> tuple[Tensor, Parts]:
    """The total loss and its parts (detached tensors, model/methods/parts.py) for one batch of
    rays; `progress` in [0, 1] drives the w_g schedule. `extra`: (name, loss) added to L_f and
    reported under its name."""
    rendered, out, edges = render_hmoe(
        model, background, rays, cfg.samples_per_ray, background_samples_per_ray, noise
    )
    deltas = edges[:, 1:] - edges[:, :-1]
    l_r = rendering_loss(rendered.rgb, rays.rgb)
    l_g = imbalanced_gate_loss(out.gate_probs, out.expert, cfg.v)
    l_d = density_loss(out.gate_probs, out.expert, out.sigma)
    w_g = log_linear(cfg.w_g, cfg.w_g_final, progress)
    loss = cfg.w_r * l_r + w_g * l_g + cfg.w_d * l_d  # L_f, section 3.3
    terms = [("rendering_loss", l_r), ("imbalanced_gate_loss", l_g), ("density_loss", l_d)]
    if cfg.w_v > 0:  # not in the paper: L_f + w_v L_v
        l_v = visibility_loss(out.gate_probs, rendered.weights)
        loss = loss + cfg.w_v * l_v
        terms.append(("visibility_loss", l_v))
    if extra is not None:
        l_x = extra[1](rendered, edges)
        loss = loss + l_x
        terms.append((extra[0], l_x))
    terms.append(("loss", loss))
    alpha = -torch.expm1(-(out.sigma.detach() * deltas.reshape(-1)))
    parts: Parts = {
        **{k: v.detach() for k, v in terms},
        "psnr": psnr(l_r),
        "samples_per_ray": float(cfg.samples_per_ray),
        "w_g": w_g,
        **gate_statistics(out.gate_probs.detach(), out.expert, out.sigma, alpha),
    }
    return loss, parts

"""Volume rendering on hard cases and the three samplers."""

import pytest
import torch

from model.estimators.guided import guided_samples
from model.render.noise import Noise
from model.render.samples import (
    inverse_cdf_edges,
    merge_edges,
    pack_edges,
    stratified_edges,
)
from model.render.volume import composite_batched, composite_packed, packed_weights

HARD_SIGMAS = [0.0, 1e-8, 1.0, 1e6]


def random_rays(r=64, n=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    choices = torch.tensor(HARD_SIGMAS)
    sigma = choices[torch.randint(0, 4, (r, n), generator=g)] * torch.rand(r, n, generator=g)
    deltas = torch.rand(r, n, generator=g) * 0.1
    deltas[0, -1] = 1e10  # the classic "last delta" of an unbounded ray
    deltas[1] = 0.0
    rgb = torch.rand(r, n, 3, generator=g)
    t_mid = deltas.cumsum(-1).clamp(max=1e3)
    return sigma, deltas, rgb, t_mid


def test_packed_equals_batched_and_is_bounded():
    sigma, deltas, rgb, t_mid = random_rays()
    r, n = sigma.shape
    bg = torch.tensor([0.2, 0.4, 0.6])
    batched = composite_batched(sigma, rgb, t_mid, deltas, bg)
    packed = composite_packed(
        sigma.reshape(-1),
        rgb.reshape(-1, 3),
        t_mid.reshape(-1),
        deltas.reshape(-1),
        torch.arange(r).repeat_interleave(n),
        r,
        bg,
    )
    assert torch.allclose(packed.rgb, batched.rgb, atol=1e-6)
    assert torch.allclose(packed.weights.reshape(r, n), batched.weights, atol=1e-7)
    for out in (packed, batched):
        assert torch.isfinite(out.rgb).all() and torch.isfinite(out.depth).all()
        assert (out.weights >= 0).all() and (out.weights <= 1).all()
        assert (out.opacity <= 1 + 1e-6).all()
    # zero-length samples: background
    assert batched.opacity[1] == 0 and torch.allclose(batched.rgb[1], bg)


def test_ray_with_no_samples_renders_the_background():
    sigma = torch.tensor([5.0, 5.0])
    out = composite_packed(
        sigma,
        torch.ones(2, 3),
        torch.tensor([1.0, 2.0]),
        torch.tensor([0.1, 0.1]),
        torch.tensor([0, 0]),
        3,
        torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.3, 0.3], [0.9, 0.1, 0.1]]),
    )
    assert torch.allclose(out.rgb[1], torch.tensor([0.3, 0.3, 0.3])) and torch.allclose(
        out.rgb[2], torch.tensor([0.9, 0.1, 0.1])
    )
    assert out.opacity[1:].tolist() == [0.0, 0.0] and out.transmittance[1:].tolist() == [1.0, 1.0]


def test_gradients_finite_on_hard_cases():
    sigma, deltas, rgb, t_mid = random_rays(seed=3)
    sigma.requires_grad_()
    rgb.requires_grad_()
    out = composite_batched(sigma, rgb, t_mid, deltas, torch.zeros(3))
    (out.rgb.sum() + out.depth.sum() * 1e-3).backward()
    assert torch.isfinite(sigma.grad).all() and torch.isfinite(rgb.grad).all()


def test_opaque_first_sample_takes_all_weight():
    w, remaining = packed_weights(
        torch.tensor([1e6, 1.0, 1.0]),
        torch.tensor([1e10, 1.0, 1.0]),
        torch.zeros(3, dtype=torch.long),
        1,
    )
    assert w.tolist() == pytest.approx([1.0, 0.0, 0.0]) and remaining.item() == 0.0


def test_bf16_inputs_render_finite():
    sigma, deltas, rgb, t_mid = random_rays(seed=4)
    out = composite_batched(
        sigma.bfloat16(), rgb.bfloat16(), t_mid.bfloat16(), deltas.bfloat16(), torch.zeros(3)
    )
    assert torch.isfinite(out.rgb.float()).all() and (out.weights.float().sum(-1) <= 1.01).all()


def test_stratified_and_inverse_cdf():
    near, far = torch.tensor([1.0, 2.0]), torch.tensor([3.0, 6.0])
    g = torch.Generator().manual_seed(0)
    edges = stratified_edges(near, far, 16, Noise(g))
    assert torch.allclose(edges[:, 0], near) and torch.allclose(edges[:, -1], far)
    assert (edges.diff(dim=-1) >= 0).all()
    weights = torch.zeros(2, 16)
    weights[:, 5] = 1.0  # all mass in bin 5
    fine = inverse_cdf_edges(edges, weights, 64, Noise(g))
    inside = (fine >= edges[:, 5:6]) & (fine <= edges[:, 6:7])
    assert inside.float().mean() > 0.9
    merged = merge_edges(edges, fine)
    assert merged.shape == (2, 16 + 1 + 64) and (merged.diff(dim=-1) >= 0).all()
    packed = pack_edges(merged)
    assert len(packed) == 2 * 80 and torch.equal(
        packed.ray_index[:80], torch.zeros(80, dtype=torch.long)
    )


def test_guided_sampler_drops_empty_bins_and_splits_kept_ones():
    origins = torch.zeros(3, 3)
    dirs = torch.tensor([[1.0, 0.0, 0.0]] * 3)
    # the third ray misses the box
    near, far = torch.tensor([0.0, 0.0, 0.0]), torch.tensor([8.0, 8.0, 0.0])
    occupied = lambda p: (p[:, 0] > 2.0) & (p[:, 0] < 4.0)  # a slab occupying [2, 4]
    samples, ratio = guided_samples(
        near,
        far,
        origins,
        dirs,
        occupied,
        num_coarse=8,
        split=4,
        noise=Noise(torch.Generator().manual_seed(0)),
    )
    # Coarse bins of width 1: midpoints 2.5 and 3.5 are occupied on rays 0 and 1 -> 2 bins x 4
    # sub-samples each.
    assert samples.ray_index.tolist() == [0] * 8 + [1] * 8
    assert (
        (samples.starts >= 2.0).all()
        and (samples.ends <= 4.0).all()
        and (samples.deltas >= 0).all()
    )
    # over the two hit rays' bins: the third has none to keep
    assert ratio.item() == pytest.approx(4 / 16)
    assert torch.allclose(samples.deltas.reshape(2, 8).sum(-1), torch.tensor([2.0, 2.0]))


def test_background_samples_and_compositing():
    from model.fields.background import BackgroundField, background_samples
    from model.render.volume import composite_batched

    far = torch.tensor([2.0, 0.0, 5.0])  # the middle ray misses the foreground box
    t, deltas = background_samples(far, 16, Noise(torch.Generator().manual_seed(0)))
    assert (t[:, 0] >= far.clamp(min=1e-2)).all() and (t.diff(dim=-1) > 0).all()
    assert torch.isfinite(t).all() and deltas[:, -1].eq(1e10).all()
    torch.manual_seed(0)
    field = BackgroundField(num_images=2, width=16, layers=2)
    origins, dirs = torch.zeros(3, 3), torch.tensor([[0.0, 0.0, 1.0]] * 3)
    xyz = origins[:, None] + dirs[:, None] * t[..., None]
    sigma, rgb = field(
        xyz.reshape(-1, 3), dirs.repeat_interleave(16, 0), torch.zeros(48, dtype=torch.long)
    )
    bg = composite_batched(sigma.reshape(3, 16), rgb.reshape(3, 16, 3), t, deltas, torch.zeros(3))
    # the opaque last sample covers the sky
    assert torch.allclose(bg.opacity, torch.ones(3), atol=1e-5)
    # Foreground with no density shows the background exactly; an opaque one hides it.
    clear = composite_batched(
        torch.zeros(3, 4), torch.ones(3, 4, 3), torch.ones(3, 4), torch.full((3, 4), 0.1), bg.rgb
    )
    opaque = composite_batched(
        torch.full((3, 4), 1e6),
        torch.ones(3, 4, 3),
        torch.ones(3, 4),
        torch.full((3, 4), 0.1),
        bg.rgb,
    )
    assert torch.allclose(clear.rgb, bg.rgb) and torch.allclose(opaque.rgb, torch.ones(3, 3))

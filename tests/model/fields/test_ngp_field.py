"""The hash-grid field (model/fields/ngp.py): its direction encoding is orthonormal, its density
activation's gradient is bounded, and the foreground and background fields answer every point with
finite values and gradients that reach their hash tables."""

import math

import torch

from model.fields.ngp import NGPBackground, NGPField, spherical_harmonics, trunc_exp

AABB = torch.tensor([[-1.0, -1.0, -0.25], [1.0, 1.0, 0.25]])
SMALL = dict(
    levels=4,
    features=2,
    log2_table_size=10,
    min_resolution=4,
    max_resolution=32,
    width=16,
    appearance_dim=4,
)


def test_the_spherical_harmonics_are_orthonormal_on_the_sphere():
    g = torch.Generator().manual_seed(0)
    d = torch.randn(400_000, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    y = spherical_harmonics(d)
    gram = 4 * math.pi * (y.T @ y) / len(d)  # Monte Carlo integral over the sphere
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=0.02)


def test_trunc_exp_is_exp_with_a_gradient_capped_at_exp_15():
    x = torch.tensor([-2.0, 0.0, 3.0, 20.0], dtype=torch.float64, requires_grad=True)
    y = trunc_exp(x)
    assert torch.allclose(y, x.detach().exp())
    y.sum().backward()
    assert torch.allclose(x.grad, torch.exp(x.detach().clamp(max=15.0)))


def test_the_fields_answer_every_point_and_their_gradients_reach_the_tables():
    torch.manual_seed(0)
    field, background = NGPField(3, AABB, **SMALL), NGPBackground(3, AABB, **SMALL)
    inside = torch.rand(256, 3) * (AABB[1] - AABB[0]) + AABB[0]
    dirs = torch.nn.functional.normalize(torch.randn(256, 3), dim=-1)
    images = torch.randint(0, 3, (256,))
    out = field(inside, dirs, images)
    assert out.sigma.shape == (256,) and out.rgb.shape == (256, 3)
    assert (out.sigma > 0).all() and ((out.rgb > 0) & (out.rgb < 1)).all()
    assert out.gate_probs.shape == (256, 1) and (out.expert == 0).all() and out.kept.all()
    far = torch.randn(256, 3) * torch.logspace(0, 8, 256)[:, None]  # out to 1e8 world units
    sigma, rgb = background(far, dirs, images)
    assert torch.isfinite(sigma).all() and torch.isfinite(rgb).all()
    (out.sigma.sum() + out.rgb.sum() + sigma.sum() + rgb.sum()).backward()
    for model in (field, background):
        table = model.hash_field.encoding.table
        assert torch.isfinite(table.grad).all() and (table.grad != 0).any()
        assert model.appearance.weight.grad is not None


def test_with_the_sky_at_infinity_two_cameras_looking_one_way_see_one_sky():
    """The opaque last background sample (the sky) lies at 2n x the box's exit distance by default,
    so cameras at different places meet it at different points of the far field; at infinity every
    ray of a direction meets one point of the contracted space, and the far field paints one colour
    there."""
    from model.fields.background import background_samples
    from model.fields.contraction import contracted_unit

    torch.manual_seed(0)
    background = NGPBackground(1, AABB, **SMALL)
    origins = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.3, 0.1]])
    dirs = torch.nn.functional.normalize(torch.tensor([[0.3, 0.2, 1.0]] * 2), dim=-1)
    far = torch.tensor([0.4, 0.9])  # each camera leaves the box at its own distance
    base, _ = background_samples(far, 8, None)
    sky = {}
    for at_infinity in (False, True):
        t, deltas = background_samples(far, 8, None, sky_at_infinity=at_infinity)
        assert deltas[:, -1].eq(1e10).all() and (t.diff(dim=-1) > 0).all()
        assert torch.equal(t[:, :-1], base[:, :-1])  # only the opaque sample moves
        last = origins + dirs * t[:, -1:]
        sky[at_infinity] = contracted_unit((last - background.centre) / background.radius)
        _, rgb = background(last, dirs, torch.zeros(2, dtype=torch.long))
        assert torch.isfinite(rgb).all()
        if at_infinity:
            assert torch.allclose(rgb[0], rgb[1], atol=1e-6)
    assert (sky[False][0] - sky[False][1]).abs().max() > 0.01
    assert torch.allclose(sky[True][0], sky[True][1], atol=1e-6)

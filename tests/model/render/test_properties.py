"""Property-based checks (hypothesis, derandomized so CI is deterministic) of rendering and the gate
losses over densities from 0 to 1e6, deltas up to 1e10, ragged packed rays and arbitrary
dispatch."""

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from model.render.losses import density_loss, imbalanced_gate_loss
from model.render.volume import composite_batched, composite_packed

SETTINGS = settings(max_examples=60, deadline=None, derandomize=True)
sigmas = st.one_of(st.sampled_from([0.0, 1e-8, 1e6]), st.floats(0, 1e6, allow_nan=False, width=32))
deltas = st.one_of(
    st.sampled_from([0.0, 1e-6, 1e10]), st.floats(0, 1e10, allow_nan=False, width=32)
)


@st.composite
def ragged_rays(draw):
    # rays with 0, 1 or many samples
    counts = draw(st.lists(st.integers(0, 6), min_size=1, max_size=6))
    total = sum(counts)
    sigma = torch.tensor(
        draw(st.lists(sigmas, min_size=total, max_size=total)), dtype=torch.float32
    )
    delta = torch.tensor(
        draw(st.lists(deltas, min_size=total, max_size=total)), dtype=torch.float32
    )
    return counts, sigma, delta


@SETTINGS
@given(ragged_rays())
def test_packed_rendering_is_bounded_finite_and_matches_batched(case):
    counts, sigma, delta = case
    r, total = len(counts), len(sigma)
    ray_index = torch.repeat_interleave(torch.arange(r), torch.tensor(counts))
    g = torch.Generator().manual_seed(0)
    rgb = torch.rand(total, 3, generator=g)
    t_mid = torch.rand(total, generator=g) * 100
    sigma.requires_grad_()
    bg = torch.tensor([0.1, 0.5, 0.9])
    out = composite_packed(sigma, rgb, t_mid, delta, ray_index, r, bg)
    assert torch.isfinite(out.rgb).all() and torch.isfinite(out.depth).all()
    assert (out.weights >= 0).all() and (out.weights <= 1).all() and (out.opacity <= 1 + 1e-6).all()
    assert torch.allclose(out.opacity + out.transmittance, torch.ones(r), atol=1e-5)
    (out.rgb.sum() + out.depth.sum()).backward()
    assert torch.isfinite(sigma.grad).all()
    # Pad every ray to the longest with zero-length samples: the batched form must agree.
    n = max(counts) if max(counts) else 1
    s_b, d_b, c_b, t_b = (
        torch.zeros(r, n),
        torch.zeros(r, n),
        torch.zeros(r, n, 3),
        torch.zeros(r, n),
    )
    start = 0
    for i, c in enumerate(counts):
        s_b[i, :c], d_b[i, :c], c_b[i, :c], t_b[i, :c] = (
            sigma.detach()[start : start + c],
            delta[start : start + c],
            rgb[start : start + c],
            t_mid[start : start + c],
        )
        start += c
    batched = composite_batched(s_b, c_b, t_b, d_b, bg)
    assert torch.allclose(batched.rgb, out.rgb.detach(), atol=1e-5)


@SETTINGS
@given(
    st.integers(1, 300),
    st.integers(1, 8),
    st.floats(-1e4, 1e4, width=32),
    st.floats(1, 200),
    st.integers(0, 2**31),
)
def test_gate_losses_finite_for_any_dispatch(points, n, logit_scale, v, seed):
    g = torch.Generator().manual_seed(seed)
    logits = (torch.randn(points, n + 1, generator=g) * logit_scale).requires_grad_()
    probs = torch.softmax(logits, -1)
    index = probs.argmax(-1)
    sigma = torch.rand(points, generator=g) * 1e6
    l_g = imbalanced_gate_loss(probs, index, v)
    l_d = density_loss(probs, index, sigma)
    (l_g + l_d).backward()
    assert torch.isfinite(l_g) and torch.isfinite(l_d) and l_d >= 0
    assert torch.isfinite(logits.grad).all()
    # every point to E_e, or none: no ratio, no division by zero
    if (index == n).all() or (index != n).all():
        assert l_d == 0

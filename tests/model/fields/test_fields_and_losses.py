"""Networks and losses: encodings, Switch-NeRF, HMoE, Eq. 1 and Eq. 2."""

import pytest
import torch

from model.fields import FrequencyEncoding, HMoE, OccupancyNetwork, SwitchNeRF
from model.fields.experts import Expert, capacity_keep, dispatch, top1
from model.methods.parts import read_parts
from model.render.losses import balance_loss, density_loss, gate_statistics, imbalanced_gate_loss


def points(n=400, seed=0, images=10):
    g = torch.Generator().manual_seed(seed)
    xyz = torch.rand(n, 3, generator=g) * 2 - 1
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return xyz, dirs, torch.randint(0, images, (n,), generator=g)


def one_hot_probs(index, experts):
    return torch.nn.functional.one_hot(index, experts).float()


def test_encoding_dimensions_and_values():
    xyz, dirs = FrequencyEncoding(12), FrequencyEncoding(4)
    assert xyz.out_dim == 75 and dirs.out_dim == 27
    x = torch.tensor([[0.5, -0.25, 0.125]])
    enc = xyz(x)
    assert enc.shape == (1, 75)
    assert torch.allclose(enc[0, :3], x[0])
    # last sine band
    assert torch.allclose(enc[0, 3 + 3 * 11 : 3 + 3 * 12], torch.sin(x[0] * 2.0**11))


def test_occupancy_network_is_about_0_15m_parameters_at_paper_width():
    count = sum(p.numel() for p in OccupancyNetwork(num_scene_experts=8, width=256).parameters())
    assert count == 153_865  # 75*256+256 + 2*(256*256+256) + 2*256 + 256*9+9


def test_imbalanced_gate_loss_optimum_is_one_at_v_over_n_plus_v():
    n, v, total = 8, 80, 8800
    counts = [100] * n + [8000]  # E_e gets v / (n + v)
    index = torch.cat([torch.full((c,), e) for e, c in enumerate(counts)])
    assert imbalanced_gate_loss(one_hot_probs(index, n + 1), index, v).item() == pytest.approx(1.0)
    everything_to_one = torch.zeros(total, dtype=torch.long)
    assert imbalanced_gate_loss(
        one_hot_probs(everything_to_one, n + 1), everything_to_one, v
    ).item() == pytest.approx(n + v)
    all_empty = torch.full((total,), n)
    assert imbalanced_gate_loss(
        one_hot_probs(all_empty, n + 1), all_empty, v
    ).item() == pytest.approx((n + v) / v)


def test_balance_loss_is_one_when_uniform():
    index = torch.arange(800) % 8
    assert balance_loss(one_hot_probs(index, 8), index).item() == pytest.approx(1.0)


def test_density_loss_detaches_sigma_and_trains_the_gate():
    torch.manual_seed(0)
    model = HMoE(num_images=10, width=32, num_scene_experts=4, expert_layers=2)
    xyz, dirs, img = points()
    out = model(xyz, dirs, img)
    assert 0 < (out.expert == 4).sum() < len(xyz)  # both groups present
    loss = density_loss(out.gate_probs, out.expert, out.sigma) + imbalanced_gate_loss(
        out.gate_probs, out.expert, v=80
    )
    loss.backward()
    assert model.gate.output.weight.grad.abs().sum() > 0  # reaches O
    # sigma is detached in L_d: no path to the heads
    assert model.scene_head.sigma.weight.grad is None
    ratio = density_loss(out.gate_probs, out.expert, out.sigma).item()
    stats = read_parts(gate_statistics(out.gate_probs, out.expert, out.sigma))
    assert ratio > 0 and stats["fraction_empty"] == pytest.approx(
        float((out.expert == 4).float().mean())
    )


def test_density_loss_with_empty_groups_is_finite_zero():
    probs = torch.softmax(torch.randn(50, 5), -1).requires_grad_()
    # all to E_e / none to E_e
    for index in (torch.full((50,), 4), torch.zeros(50, dtype=torch.long)):
        loss = density_loss(probs, index, torch.rand(50))
        loss.backward()
        assert loss.item() == 0.0 and torch.isfinite(probs.grad).all()
    stats = read_parts(gate_statistics(probs.detach(), torch.full((50,), 4), torch.rand(50)))
    # NaN, no crash
    assert stats["fraction_empty"] == 1.0 and stats["density_scene"] != stats["density_scene"]


def test_switch_dispatch_equals_dense_evaluation():
    torch.manual_seed(1)
    model = SwitchNeRF(num_images=10, width=32, num_experts=4, expert_layers=3).eval()
    xyz, dirs, img = points(200)
    out = model(xyz, dirs, img)
    h = model.input_layer(model.xyz_encoding(xyz))
    dense = torch.stack([e(h) for e in model.experts], 1)  # every expert on every point
    chosen = out.gate_probs.gather(1, out.expert[:, None])
    mixed = torch.relu(dense[torch.arange(200), out.expert] * chosen)
    _, sigma, rgb = model.head(mixed, model.dir_encoding(dirs), model.appearance(img))
    assert torch.allclose(out.sigma, sigma, atol=1e-6) and torch.allclose(out.rgb, rgb, atol=1e-6)


def test_dispatch_matches_each_expert_on_its_own_points_in_value_and_gradient():
    torch.manual_seed(3)
    experts = torch.nn.ModuleList(Expert(16, layers=2, residual_at=0) for _ in range(4))
    h = torch.randn(300, 16, requires_grad=True)
    index = torch.randint(0, 3, (300,))  # expert 3 gets no points
    keep = torch.rand(300) > 0.2
    out = dispatch(experts, h, index, keep)
    for e in range(4):
        mine = (index == e) & keep
        if mine.any():
            assert torch.allclose(out[mine], experts[e](h[mine]), atol=1e-6)
    assert (out[~keep] == 0).all()
    out.square().sum().backward()
    grad_h = h.grad.clone()
    h.grad = None
    reference = torch.zeros(300, 16)
    for e in range(3):
        mine = (index == e) & keep
        reference = reference.index_put((mine.nonzero().squeeze(1),), experts[e](h[mine]))
    experts.zero_grad()
    reference.square().sum().backward()
    assert torch.allclose(grad_h, h.grad, atol=1e-5)
    assert (grad_h[~keep] == 0).all()
    empty = dispatch(experts, h[:0], index[:0], keep[:0])
    assert empty.shape == (0, 16)


def gather_per_expert(experts, h, index, keep):
    """The dispatch the sort-and-segment one replaced: a gather, a run and a scatter per expert."""
    out = h.new_zeros(h.shape)
    for e, expert in enumerate(experts):
        members = torch.nonzero((index == e) & keep).squeeze(1)
        if len(members):
            out = out.index_copy(0, members, expert(h[members]))
    return out


def test_dispatch_is_bit_for_bit_the_gather_per_expert_in_value_and_every_gradient():
    torch.manual_seed(5)
    experts = torch.nn.ModuleList(Expert(32, layers=3, residual_at=1) for _ in range(5))
    index = torch.randint(0, 4, (777,))  # expert 4 gets no points
    keep = torch.rand(777) > 0.1
    results = []
    for fn in (dispatch, gather_per_expert):
        experts.zero_grad(set_to_none=True)
        h = torch.randn(777, 32, generator=torch.Generator().manual_seed(9), requires_grad=True)
        out = fn(experts, h, index, keep)
        (out.sin() * torch.arange(32)).sum().backward()
        grads = [p.grad.clone() if p.grad is not None else None for p in experts.parameters()]
        results.append((out.detach(), h.grad.clone(), grads))
    (out_a, h_a, grads_a), (out_b, h_b, grads_b) = results
    assert torch.equal(out_a, out_b) and torch.equal(h_a, h_b)
    assert all((a is None and b is None) or torch.equal(a, b) for a, b in zip(grads_a, grads_b))
    assert all(p.grad is None for p in experts[4].parameters())  # no points, no gradient


def test_capacity_drops_least_confident_overflow():
    index = torch.tensor([0, 0, 0, 0, 1, 0])
    chosen = torch.tensor([0.9, 0.5, 0.8, 0.6, 0.7, 0.95])
    # capacity ceil(6/2) = 3
    keep = capacity_keep(index, chosen, num_experts=2, capacity_factor=1.0)
    assert keep.tolist() == [True, False, True, False, True, True]
    assert capacity_keep(index, chosen, 2, None).all()


def test_top1_ties_and_huge_logits():
    probs, index, chosen = top1(torch.tensor([[1e4, 1e4, -1e4], [-1e4, 0.0, 1e4]]))
    assert index.tolist() == [0, 2] and torch.isfinite(probs).all()
    assert chosen.tolist() == pytest.approx([0.5, 1.0])


def test_hmoe_empty_points_use_the_empty_head_and_homogeneous_switch():
    torch.manual_seed(2)
    model = HMoE(num_images=10, width=32, num_scene_experts=4, expert_layers=2).eval()
    xyz, dirs, img = points(300)
    out = model(xyz, dirs, img)
    empty = out.expert == 4
    h, _ = model.gate.features_and_logits(xyz[empty])
    _, sigma, rgb = model.empty_head(h * out.gate_probs[empty, 4:5])
    assert torch.allclose(out.sigma[empty], sigma, atol=1e-6) and torch.allclose(
        out.rgb[empty], rgb, atol=1e-6
    )
    assert torch.equal(model.gate.occupied(xyz), ~empty)
    heavy = HMoE(num_images=10, width=32, num_scene_experts=4, expert_layers=2, homogeneous=True)
    extra = sum(p.numel() for p in heavy.empty_expert.parameters())
    assert (
        extra == 2 * (32 * 32 + 32) and sum(p.numel() for p in model.empty_expert.parameters()) == 0
    )
    # Table 9
    four = HMoE(
        num_images=10, width=32, num_scene_experts=4, expert_layers=2, empty_expert_layers=4
    )
    assert sum(p.numel() for p in four.empty_expert.parameters()) == 4 * (32 * 32 + 32)
    assert four(xyz, dirs, img).sigma.shape == (300,)


def test_bf16_autocast_keeps_the_gate_in_fp32():
    model = SwitchNeRF(num_images=10, width=32, num_experts=4, expert_layers=2)
    xyz, dirs, img = points(64)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(xyz, dirs, img)
        logits = model.gate(model.input_layer(model.xyz_encoding(xyz)))
    assert logits.dtype == torch.float32 and out.gate_probs.dtype == torch.float32
    assert torch.isfinite(out.sigma.float()).all() and torch.isfinite(out.rgb.float()).all()

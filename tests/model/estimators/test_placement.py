"""O places the main network's samples (model/estimators/placement.py) and what reaches the main
network is counted alike for every method (model/render/accounting.py)."""

import pytest
import torch

from model.estimators.guided import guided_samples
from model.estimators.placement import (
    bin_mass,
    confident_bins,
    explored,
    placed_samples,
    placement_loss,
)
from model.fields.hmoe import OccupancyNetwork
from model.methods.parts import read_parts
from model.render.accounting import step_accounting, surface_accounting
from model.render.noise import Noise
from model.render.samples import PackedSamples, stratified_edges
from model.render.volume import batched_weights, packed_weights


def coarse(r=5, bins=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    near = torch.rand(r, generator=g)
    far = near + 4.0 + torch.rand(r, generator=g)
    return near, far, stratified_edges(near, far, bins, None)


@pytest.mark.parametrize("noise", [None, Noise(torch.Generator().manual_seed(3))])
def test_placed_samples_are_exactly_n_per_ray_sorted_and_inside_the_kept_bins(noise):
    near, far, edges = coarse()
    keep = torch.zeros(5, 8, dtype=torch.bool)
    keep[:, [1, 2, 5]] = True  # kept bins need not touch
    keep[0] = False
    keep[0, 7] = True  # one ray keeps its last bin only
    weights = torch.rand(5, 8, generator=torch.Generator().manual_seed(1)) + 0.01
    samples = placed_samples(edges, keep, weights, 21, noise)
    assert len(samples) == 5 * 21 and samples.ray_index.tolist() == [
        r for r in range(5) for _ in range(21)
    ]
    mids = samples.mids.reshape(5, 21)
    assert (mids[:, 1:] > mids[:, :-1]).all(), "sorted along each ray"
    assert (mids >= near[:, None]).all() and (mids <= far[:, None]).all()
    assert (samples.deltas > 0).all()
    width = (far - near) / 8
    bin_of = ((mids - near[:, None]) / width[:, None]).floor().long().clamp(0, 7)
    assert keep.gather(1, bin_of).all(), "every mid-point inside a kept bin"
    # The deltas tile the kept length (the first and last intervals stop at the jittered CDF's
    # ends).
    kept_length = keep.sum(1) * width
    assert (samples.deltas.reshape(5, 21).sum(1) <= kept_length + 1e-5).all()
    if noise is None:
        assert torch.allclose(samples.deltas.reshape(5, 21).sum(1), kept_length, atol=1e-5)


def test_placed_samples_follow_the_weights():
    near, far, edges = coarse(r=1)
    keep = torch.tensor([[False, True, True, False, False, True, False, False]])
    weights = torch.tensor([[0.0, 0.1, 0.8, 0.0, 0.0, 0.1, 0.0, 0.0]])
    samples = placed_samples(edges, keep, weights, 20, None)
    bin_of = ((samples.mids - near) / ((far - near) / 8)).floor().long()
    assert torch.bincount(bin_of, minlength=8).tolist() == [0, 2, 16, 0, 0, 2, 0, 0]


def test_bins_below_the_minimum_share_get_no_sample_and_every_ray_keeps_one():
    keep = torch.tensor(
        [[True, True, True, False], [True, True, False, False], [True, True, False, False]]
    )
    weights = torch.tensor([[0.01, 0.5, 0.49, 0.9], [0.001, 0.002, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    kept = confident_bins(keep, weights, 0.03)
    # Row 0: the bin with 1% of the kept mass goes (the unkept bin's weight does not count); row 1:
    # shares are relative (33% and 67%), both stay; row 2: no weight to judge by, all stay.
    assert kept.tolist() == [
        [False, True, True, False],
        [True, True, False, False],
        [True, True, False, False],
    ]
    assert confident_bins(keep, weights, 0.5).tolist() == [
        [False, True, False, False],
        [False, True, False, False],
        # the heaviest survives
        [True, True, False, False],
    ]
    assert torch.equal(confident_bins(keep, weights, 0.0), keep)
    near, far, edges = coarse(r=3, bins=4)
    samples = placed_samples(
        edges, kept, weights + 0.01, 9, Noise(torch.Generator().manual_seed(0))
    )
    bin_of = (
        ((samples.mids - near[samples.ray_index]) / ((far - near) / 4)[samples.ray_index])
        .floor()
        .long()
    )
    assert (
        kept[samples.ray_index, bin_of.clamp(0, 3)].all()
        and not (bin_of[samples.ray_index == 0] == 0).any()
    )


def test_exploration_gives_the_dropped_bins_their_share_of_the_samples():
    near, far, edges = coarse(r=2, bins=8)
    keep = torch.zeros(2, 8, dtype=torch.bool)
    keep[0, [2, 3]] = True
    keep[1] = True  # a ray that keeps every bin has nothing to explore
    mass = torch.rand(2, 8, generator=torch.Generator().manual_seed(2)) + 0.01
    unchanged = explored(keep, mass, edges, 0.0)
    # share 0: the kept bins and the mass as they were
    assert unchanged[0] is keep and unchanged[1] is mass
    everywhere, spread = explored(keep, mass, edges, 0.2)
    assert (
        everywhere.all()
        and torch.equal(spread[1], mass[1])
        and torch.equal(spread[0, [2, 3]], mass[0, [2, 3]])
    )
    # the dropped bins' share
    assert float(spread[0, ~keep[0]].sum() / spread[0].sum()) == pytest.approx(0.2)
    assert torch.allclose(spread[0, ~keep[0]], spread[0, 0].expand(6))  # equal lengths, equal mass
    samples = placed_samples(edges, everywhere, spread, 200, None)
    mids = samples.mids.reshape(2, 200)
    assert (
        (mids[:, 1:] > mids[:, :-1]).all()
        and (mids >= near[:, None]).all()
        and (mids <= far[:, None]).all()
    )
    bin_of = ((mids - near[:, None]) / ((far - near) / 8)[:, None]).floor().long().clamp(0, 7)
    # 20% of the samples where O dropped the bins (give or take the interval that straddles a
    # boundary)
    assert abs(int((~keep[0][bin_of[0]]).sum()) - 40) <= 1


def test_the_placement_loss_is_the_interlevel_bound_and_trains_only_the_proposal():
    near, far = torch.zeros(1), torch.full((1,), 4.0)
    samples = PackedSamples(
        torch.tensor([0.5, 2.0, 2.5]),
        torch.tensor([1.0, 2.5, 3.0]),
        torch.zeros(3, dtype=torch.long),
    )
    main = torch.tensor([0.1, 0.3, 0.4], requires_grad=True)
    assert bin_mass(samples, main, near, far, 4).tolist() == [
        [pytest.approx(0.1), 0.0, pytest.approx(0.7), 0.0]
    ]
    bound = torch.tensor([[0.2, 0.0, 0.7, 0.1]])
    assert float(placement_loss(bound, samples, main, near, far)) == pytest.approx(0.0, abs=1e-6)
    low = torch.tensor([[0.1, 0.0, 0.35, 0.0]], requires_grad=True)
    loss = placement_loss(low, samples, main, near, far)
    # only bin 2 exceeds its bound
    assert float(loss.detach()) == pytest.approx(0.35**2 / 0.7 / 4, rel=1e-4)
    loss.backward()
    # the proposal is pushed up where it is short
    assert main.grad is None and float(low.grad[0, 2]) < 0


def test_o_s_placement_head_learns_where_a_wall_holds_the_weight():
    torch.manual_seed(0)
    network = OccupancyNetwork(
        num_scene_experts=2, width=32, xyz_frequencies=4, placement_head=True
    )
    optimizer = torch.optim.Adam(network.parameters(), lr=1e-2)
    near, far = torch.zeros(64), torch.full((64,), 8.0)
    dirs = torch.tensor([1.0, 0.0, 0.0]).expand(64, 3)
    edges = stratified_edges(near, far, 8, None)
    mids = 0.5 * (edges[:, 1:] + edges[:, :-1])
    points = (dirs[:, None] * mids[..., None]).reshape(-1, 3)
    # The main network's weight: everything in the wall at x in [4.2, 4.8] (coarse bin 4).
    samples = PackedSamples(torch.full((64,), 4.2), torch.full((64,), 4.8), torch.arange(64))
    main = torch.ones(64)
    for _ in range(200):
        sigma = network.query(points)[1].reshape(64, 8)
        proposal = batched_weights(sigma, edges[:, 1:] - edges[:, :-1])[0]
        loss = placement_loss(proposal, samples, main, near, far)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        sigma = network.query(points)[1].reshape(64, 8)
        proposal = batched_weights(sigma, edges[:, 1:] - edges[:, :-1])[0]
    assert float(proposal[:, 4].mean()) > 0.9
    drawn = placed_samples(edges, torch.ones(64, 8, dtype=torch.bool), proposal + 0.01, 21, None)
    in_wall_bin = ((drawn.mids >= 4.0) & (drawn.mids < 5.0)).float().mean()
    assert float(in_wall_bin) > 0.6  # the split sampler would give that bin 1/8 of a ray's samples


def test_accounting_counts_hit_rays_dilation_and_rays_with_nothing_kept():
    # Ray 0 keeps bin 3 (dilated to 2..4), ray 1 keeps nothing, ray 2 misses the box.
    near = torch.tensor([0.0, 0.0, 1.0])
    far = torch.tensor([8.0, 8.0, 1.0])
    origins, dirs = torch.zeros(3, 3), torch.tensor([1.0, 0.0, 0.0]).expand(3, 3)
    occupied = lambda points: (points[:, 0] > 3.0) & (points[:, 0] < 4.0) & (points[:, 1] == 0)
    dirs = dirs.clone()
    dirs[1] = torch.tensor([0.0, 1.0, 0.0])  # ray 1 looks along y: O keeps nothing there
    samples, kept = guided_samples(near, far, origins, dirs, occupied, 8, 2, None, dilate=1)
    figures = read_parts(step_accounting(samples, near, far, 8))
    assert float(kept) == pytest.approx(1 / 16)  # O itself: one bin of the two hit rays' 16
    # after dilation: three bins reach the main network
    assert figures["occupancy_ratio"] == pytest.approx(3 / 16)
    assert figures["samples_per_hit_ray"] == pytest.approx(6 / 2)
    assert figures["hit_ray_fraction"] == pytest.approx(2 / 3)
    with_fallback, _ = guided_samples(
        near, far, origins, dirs, occupied, 8, 2, None, dilate=1, fallback=True
    )
    with_fallback_figures = read_parts(step_accounting(with_fallback, near, far, 8))
    assert with_fallback_figures["occupancy_ratio"] == pytest.approx(11 / 16)


def test_surface_accounting_finds_the_surface_bin_and_the_foreground_opacity():
    near, far = torch.zeros(3), torch.full((3,), 8.0)
    samples = PackedSamples(
        torch.tensor([3.0, 3.5, 6.0]), torch.tensor([3.5, 4.0, 6.5]), torch.tensor([0, 0, 1])
    )
    sigma = torch.tensor([2.0, 2.0, 0.5])
    weights, _ = packed_weights(sigma, samples.deltas, samples.ray_index, 3)
    # ray 1's surface lies in bin 2, which it never sampled
    depth = torch.tensor([3.4, 2.0, torch.inf])
    out = surface_accounting(samples, weights, near, far, depth, 8)
    assert out["surface"].tolist() == [True, True, False]
    assert out["kept"].tolist() == [True, False, False]
    assert float(out["opacity"][0]) == pytest.approx(
        1 - torch.exp(torch.tensor(-2.0)).item(), rel=1e-5
    )


def test_a_guided_option_without_its_switch_is_refused_naming_both():
    from pydantic import ValidationError

    from model.profiles import GuidedConfig

    with pytest.raises(ValidationError, match="guided.fallback_topk needs guided.fallback=true"):
        GuidedConfig(fallback_topk=2)
    with pytest.raises(
        ValidationError, match="guided.placement_in_phase1 needs guided.placement=true"
    ):
        GuidedConfig(placement_in_phase1=True)
    with pytest.raises(ValidationError, match="guided.placement_every needs guided.placement=true"):
        GuidedConfig(placement_every=5)
    with pytest.raises(
        ValidationError, match="guided.placement_explore needs guided.placement=true"
    ):
        GuidedConfig(placement_explore=0.05)
    with pytest.raises(ValidationError, match="use guided.placement_explore instead"):
        GuidedConfig(placement=True, explore_bins=2)
    from model.profiles import LeCOPropConfig

    with pytest.raises(ValidationError, match="look outside O's bound with leco_prop.explore"):
        LeCOPropConfig(guided=GuidedConfig(explore_bins=2))
    assert GuidedConfig(explore_bins=2).explore_bins == 2
    assert (
        GuidedConfig(
            fallback=True, fallback_topk=2, placement=True, placement_in_phase1=True
        ).fallback_topk
        == 2
    )


def test_within_bin_shares_keep_each_bins_mass_and_take_the_shape_asked():
    from model.estimators.placement import within_bin_shares

    edges = torch.tensor([[0.0, 1.0, 2.0, 3.0, 4.0]])
    mass = torch.tensor([[0.1, 1.0, 4.0, 0.0]])  # the last bin dropped (no mass)
    sigma = torch.tensor([[0.0, 0.01, 50.0, 50.0]])
    for kind in ("uniform", "linear", "volume"):
        shares = within_bin_shares(kind, mass, sigma, edges, k=4)
        assert shares.shape == (1, 4, 4) and torch.allclose(shares.sum(-1), torch.ones(1, 4))
    assert torch.equal(
        within_bin_shares("uniform", mass, sigma, edges, k=4), torch.full((1, 4, 4), 0.25)
    )
    linear = within_bin_shares("linear", mass, sigma, edges, k=4)[0]
    # bin 1 lies between a light bin and a heavy one: its density rises towards the heavy one
    assert (linear[1, 1:] > linear[1, :-1]).all()
    # the heavy bin 2 has the dropped bin behind it: it falls towards it
    assert (linear[2, 1:] < linear[2, :-1]).all()
    volume = within_bin_shares("volume", mass, sigma, edges, k=4)[0]
    assert torch.allclose(volume[0], torch.full((4,), 0.25))  # no density: evenly
    assert torch.allclose(volume[1], torch.full((4,), 0.25), atol=2e-3)  # faint: nearly evenly
    # opaque (tau 50): the weight is at the bin's front, as volume rendering puts it
    assert volume[2, 0] > 0.99
    with pytest.raises(ValueError, match="within-bin shape 'cubic'"):
        within_bin_shares("cubic", mass, sigma, edges)


@pytest.mark.parametrize("kind", ["linear", "volume"])
def test_a_shaped_draw_is_still_exactly_n_per_ray_sorted_inside_the_kept_bins(kind):
    from model.estimators.placement import subdivided, within_bin_shares

    near, far, edges = coarse()
    keep = torch.zeros(5, 8, dtype=torch.bool)
    keep[:, [1, 2, 5]] = True
    mass = (torch.rand(5, 8, generator=torch.Generator().manual_seed(1)) + 0.01) * keep
    sigma = torch.full((5, 8), 30.0)
    shares = within_bin_shares(kind, mass, sigma, edges)
    fine_edges, fine_keep, fine_mass = subdivided(edges, keep, mass, shares)
    assert fine_edges.shape == (5, 33) and torch.allclose(fine_mass.reshape(5, 8, 4).sum(-1), mass)
    samples = placed_samples(
        fine_edges, fine_keep, fine_mass, 21, Noise(torch.Generator().manual_seed(2))
    )
    mids = samples.mids.reshape(5, 21)
    assert (mids[:, 1:] > mids[:, :-1]).all() and (samples.deltas > 0).all()
    width = (far - near) / 8
    position = (mids - near[:, None]) / width[:, None]
    assert keep.gather(1, position.floor().long().clamp(0, 7)).all()
    if kind == "volume":  # opaque bins: the samples crowd each kept bin's front quarter
        assert (position.frac() < 0.25).float().mean() > 0.9


def test_a_within_bin_shape_needs_the_one_pass_placement():
    from model.profiles import GuidedConfig

    assert GuidedConfig(placement=True, placement_within="volume").placement_within == "volume"
    with pytest.raises(ValueError, match="guided.placement_within needs guided.placement=true"):
        GuidedConfig(placement_within="linear")
    with pytest.raises(ValueError, match="placement_fine=0"):
        GuidedConfig(placement=True, placement_fine=8, placement_within="linear")

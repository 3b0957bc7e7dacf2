"""O's second placement pass (model/estimators/fine_placement.py): exactly n samples per ray,
sorted, inside the kept bins, drawn where O's density at sub-bin resolution says the weight is; its
interlevel loss trains O only."""

import pytest
import torch

from model.estimators.fine_placement import fine_placement_loss, fine_samples, kept_axis, to_t
from model.render.noise import Noise
from model.render.samples import stratified_edges


def rows(r=4, bins=8):
    near = torch.zeros(r)
    far = torch.full((r,), 8.0)
    return stratified_edges(near, far, bins, None)  # bins of length 1: bin k is [k, k + 1)


def wall_at(depth: float, width: float = 0.05):
    def density(t):
        return torch.where(
            (t - depth).abs() < width, torch.full_like(t, 200.0), torch.zeros_like(t)
        )

    return density


def test_the_kept_axis_skips_dropped_bins_and_maps_back():
    edges = rows(1)
    keep = torch.tensor([[False, True, True, False, False, True, False, False]])
    s_edges = kept_axis(edges, keep)
    assert s_edges[0].tolist() == [0, 0, 1, 2, 2, 2, 3, 3, 3]
    assert to_t(torch.tensor([[0.5, 1.5, 2.5]]), s_edges, edges).tolist() == [[1.5, 2.5, 5.5]]


@pytest.mark.parametrize("noise", [None, Noise(torch.Generator().manual_seed(0))])
def test_fine_samples_are_n_per_ray_sorted_inside_kept_bins_and_gather_at_o_s_surface(noise):
    edges = rows()
    keep = torch.zeros(4, 8, dtype=torch.bool)
    keep[:, [2, 3, 6]] = True
    weights = torch.tensor([[0, 0, 0.1, 0.8, 0, 0, 0.1, 0.0]]).expand(4, 8)
    samples, draw = fine_samples(
        torch.arange(4), edges, keep, weights + 0.01, 32, 21, wall_at(3.3), noise, 1.0, 0.01
    )
    assert len(samples) == 4 * 21 and draw.main.shape == (4, 22) and draw.coarse.shape == (4, 33)
    mids = samples.mids.reshape(4, 21)
    assert (mids[:, 1:] >= mids[:, :-1]).all() and (samples.deltas >= 0).all()
    assert keep.gather(1, mids.floor().long().clamp(0, 7)).all(), "every sample in a kept bin"
    near_wall = ((mids - 3.3).abs() < 0.1).sum(1).float().mean()
    assert near_wall >= 12, f"most samples at O's wall inside bin 3, got {near_wall:.1f} of 21"
    one_pass_share = 21 * 0.8 * 0.2  # evenly inside bin 3 (0.8 of the mass), 0.2 of its length
    assert near_wall > 2 * one_pass_share


def test_the_fine_loss_is_the_interlevel_bound_and_trains_only_o():
    edges = rows(2)
    keep = torch.ones(2, 8, dtype=torch.bool)
    _, draw = fine_samples(
        torch.arange(2), edges, keep, torch.ones(2, 8), 16, 8, wall_at(4.0), None, 1.0, 0.01
    )
    raw = torch.zeros(2, 16, requires_grad=True)  # O's densities at the intermediate mid-points
    main = torch.zeros(2, 8)
    main[:, 4] = 0.9  # the main network's weight sits where O says nothing: the bound is violated
    loss = fine_placement_loss(draw, torch.nn.functional.softplus(raw), main)
    assert float(loss.detach()) > 0
    loss.backward()
    assert raw.grad is not None and raw.grad.abs().sum() > 0
    lo, hi = draw.main[:, 4:5], draw.main[:, 5:6]
    overlaps = (draw.coarse[:, 1:] > lo) & (draw.coarse[:, :-1] < hi)
    # O's weight where the main's is
    wall = torch.where(overlaps, torch.full((2, 16), 1e3), torch.zeros(2, 16))
    assert float(fine_placement_loss(draw, wall, main)) == pytest.approx(0.0, abs=1e-9)

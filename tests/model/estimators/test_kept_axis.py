"""The axis a bounded proposal sampler draws on (model/estimators/kept_axis.py): its forms, and that
every coordinate on it lands in a bin it runs over."""

import pytest
import torch

from model.estimators.kept_axis import KeptAxis, SegmentAxis, bounded

KEEP = torch.tensor(
    [
        [False, True, False, False, True, False],  # two kept bins apart
        [True, True, True, True, True, True],  # all
        [False, False, False, False, False, True],  # the last only
        [False, False, False, False, False, False],  # nothing (a miss, no fallback)
    ]
)


def test_range_fills_from_the_first_kept_bin_to_the_last_mask_keeps_and_off_takes_all():
    assert bounded(KEEP, "range").tolist() == [
        [False, True, True, True, True, False],
        [True] * 6,
        [False] * 5 + [True],
        [False] * 6,
    ]
    assert torch.equal(bounded(KEEP, "mask"), KEEP)
    assert bounded(KEEP, "off").all()
    with pytest.raises(ValueError, match="unknown bound 'box': choose one of range, mask, off"):
        bounded(KEEP, "box")


def test_every_coordinate_of_the_axis_lands_in_a_bin_it_runs_over():
    edges = torch.linspace(2.0, 8.0, 7).expand(4, 7).contiguous()  # bins one unit long
    axis = KeptAxis.of(edges, KEEP)
    assert axis.length().tolist() == [2.0, 6.0, 1.0, 0.0]
    # dense coordinates over each ray's axis, both ends included
    s = axis.start[:, None] + (axis.end - axis.start)[:, None] * torch.linspace(0, 1, 101)
    t = axis.to_t(s)
    bin_ = ((t - 2.0).floor().long()).clamp(0, 5)
    inside = KEEP.gather(1, bin_) | ((t - 2.0) == bin_.float())  # a boundary of a kept bin counts
    assert inside[:3].all()
    # the two kept bins apart: s in [0, 1] is bin 1 ([3, 4]), s in (1, 2] bin 4 ([6, 7])
    assert axis.to_t(torch.tensor([[0.0, 0.5, 1.0, 1.5, 2.0]] * 4))[0].tolist() == [
        3.0,
        3.5,
        6.0,
        6.5,
        7.0,
    ]
    # the end of the axis is the end of the last kept bin, not a dropped bin after it
    assert float(axis.to_t(axis.end[:, None])[0, 0]) == 7.0
    # on the whole segment, s is t less the start
    full = KeptAxis.of(edges, torch.ones_like(KEEP))
    assert torch.allclose(full.to_t(s[1].expand(4, -1)), s[1] + 2.0)


def test_the_segment_axis_is_the_ray_itself():
    near, far = torch.tensor([1.0, 2.0]), torch.tensor([3.0, 5.0])
    axis = SegmentAxis(near, far)
    x = torch.rand(2, 5)
    assert axis.to_t(x) is x and axis.start is near and axis.end is far


def test_with_explore_a_dropped_bin_keeps_a_share_of_its_length_and_maps_back_to_itself():
    edges = torch.linspace(2.0, 8.0, 7).expand(4, 7).contiguous()
    axis = KeptAxis.of(edges, KEEP, explore=0.1)
    # two kept bins of 1 and four dropped of 0.1; a ray that keeps nothing gets no length at all
    assert torch.allclose(axis.length(), torch.tensor([2.4, 6.0, 1.5, 0.0]))
    # the first dropped bin ([2, 3]) is s in [0, 0.1]: its middle is t = 2.5; the kept bin after
    # it ([3, 4]) is s in [0.1, 1.1]
    t = axis.to_t(torch.tensor([[0.05, 0.6, 1.15, 2.35]] * 4))[0]
    assert torch.allclose(t, torch.tensor([2.5, 3.5, 4.5, 7.5]))
    # a uniform draw puts about 0.4 / 2.4 of its samples in the dropped bins
    s = torch.rand(1, 20_000) * 2.4
    t = axis.to_t(torch.cat([s, s, s, s]))[0]
    in_dropped = ~KEEP[0][(t - 2.0).floor().long().clamp(0, 5)]
    assert abs(float(in_dropped.float().mean()) - 0.4 / 2.4) < 0.01

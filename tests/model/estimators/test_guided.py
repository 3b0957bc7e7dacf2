"""The guided sampler's options: jittered queries, dilation, the fallback for rays with nothing
kept. Every option must keep the packed invariants: samples grouped by ray in increasing t, inside
[near, far]."""

import pytest
import torch

from model.estimators.guided import dilate_bins, guided_samples
from model.estimators.occupancy import OccupancyQuery
from model.fields.hmoe import OccupancyNetwork
from model.render.noise import Noise

# a thin wall at x in [2, 2.2]: between the mid-points 1.5 and 2.5 of unit coarse bins
SLAB = (2.0, 2.2)


def rays(n=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    origins = torch.zeros(n, 3)
    dirs = torch.nn.functional.normalize(
        torch.randn(n, 3, generator=g).abs() + torch.tensor([3.0, 0, 0]), dim=-1
    )
    near = torch.rand(n, generator=g) * 0.5
    far = near + 6.0 + torch.rand(n, generator=g)
    far[:4] = near[:4]  # rays that miss the box
    return near, far, origins, dirs


def wall(points):
    return (points[:, 0] > SLAB[0]) & (points[:, 0] < SLAB[1])


def nothing(points):
    return torch.zeros(len(points), dtype=torch.bool)


class KeepEverything(OccupancyQuery):
    """An O that keeps every point (its decision logit is 1 everywhere)."""

    def __init__(self):
        super().__init__(OccupancyNetwork(2, 8, 2), None)

    def occupied(self, points):
        self.logits = torch.tensor([[1.0, 0.0, 0.0]]).expand(len(points), 3)
        return torch.ones(len(points), dtype=torch.bool)


def check_invariants(samples, near, far):
    i = samples.ray_index
    assert (i[1:] >= i[:-1]).all(), "samples are grouped by ray"
    same = i[1:] == i[:-1]
    assert (samples.starts[1:][same] >= samples.ends[:-1][same] - 1e-6).all(), (
        "increasing t along each ray"
    )
    assert (samples.ends >= samples.starts).all()
    assert (samples.starts >= near[i] - 1e-6).all() and (samples.ends <= far[i] + 1e-6).all(), (
        "inside [near, far]"
    )


@pytest.mark.parametrize(
    "options",
    [
        {},
        {"jitter": True},
        {"dilate": 1},
        {"fallback": True},
        {"jitter": True, "dilate": 2, "fallback": True},
        {"dilate": 1, "fallback": True, "topk": 2, "explore": 2},
    ],
)
def test_every_option_keeps_samples_sorted_and_inside_the_segment(options):
    near, far, origins, dirs = rays()
    for occupied in (wall, nothing):
        samples, ratio = guided_samples(
            near,
            far,
            origins,
            dirs,
            occupied,
            8,
            4,
            Noise(torch.Generator().manual_seed(1)),
            **options,
        )
        check_invariants(samples, near, far)
        assert 0 <= float(ratio) <= 1
        assert not torch.isin(torch.arange(4), samples.ray_index).any(), (
            "rays that miss the box get nothing"
        )


def test_jittered_queries_find_a_wall_between_mid_points():
    n = 60
    # unit coarse bins along x: mid-points 0.5, 1.5, 2.5, ...
    near, far = torch.zeros(n), torch.full((n,), 8.0)
    origins = torch.stack([torch.zeros(n), torch.linspace(-1, 1, n), torch.zeros(n)], -1)
    dirs = torch.tensor([[1.0, 0.0, 0.0]]).expand(n, 3)
    fixed, _ = guided_samples(
        near, far, origins, dirs, wall, 8, 4, Noise(torch.Generator().manual_seed(0))
    )
    assert len(fixed) == 0  # mid-point queries never see the thin wall
    hits, g = torch.zeros(n, dtype=torch.bool), torch.Generator().manual_seed(0)
    for _ in range(30):
        jittered, _ = guided_samples(near, far, origins, dirs, wall, 8, 4, Noise(g), jitter=True)
        check_invariants(jittered, near, far)
        hits[jittered.ray_index] = True
    assert hits.all()  # every ray samples the wall on some step (p = 0.2 per step)
    # Without a generator (validation) jitter is off: the same samples as the paper's sampler.
    a, _ = guided_samples(*rays(), wall, 8, 4, None, jitter=True)
    b, _ = guided_samples(*rays(), wall, 8, 4, None)
    assert torch.equal(a.starts, b.starts) and torch.equal(a.ray_index, b.ray_index)


def test_several_queries_per_bin_find_a_ground_that_fills_the_far_end_of_the_last_bin():
    # The ground fills x > 7.7 of a [0, 8] segment in 8 bins: the last bin's mid-point (7.5) is in
    # the air above it.
    near, far, origins, dirs = rays()
    near, far = torch.zeros_like(near), torch.full_like(far, 8.0)
    dirs = torch.tensor([1.0, 0.0, 0.0]).expand(len(near), 3)
    ground = lambda points: points[:, 0] > 7.7
    one, _ = guided_samples(near, far, origins, dirs, ground, 8, 4, None)
    assert len(one) == 0
    # 7.125 ... 7.875
    four, ratio = guided_samples(near, far, origins, dirs, ground, 8, 4, None, queries=4)
    check_invariants(four, near, far)
    assert (
        len(four) == len(near) * 4 and (four.starts >= 7.0 - 1e-6).all() and float(ratio) == 1 / 8
    )


def test_dilation_keeps_the_neighbours_of_kept_bins():
    keep = torch.tensor(
        [[0, 0, 0, 1, 0, 0, 0, 0], [1, 0, 0, 0, 0, 0, 0, 1], [0] * 8], dtype=torch.bool
    )
    assert dilate_bins(keep, 0).equal(keep)
    assert dilate_bins(keep, 1).int().tolist() == [
        [0, 0, 1, 1, 1, 0, 0, 0],
        [1, 1, 0, 0, 0, 0, 1, 1],
        [0] * 8,
    ]
    assert dilate_bins(keep, 2)[0].int().tolist() == [0, 1, 1, 1, 1, 1, 0, 0]
    near, far, origins, dirs = (
        torch.zeros(1),
        torch.full((1,), 8.0),
        torch.zeros(1, 3),
        torch.tensor([[1.0, 0, 0]]),
    )
    slab = lambda p: (p[:, 0] > 3.0) & (p[:, 0] < 4.0)  # only the bin [3, 4)
    samples, ratio = guided_samples(near, far, origins, dirs, slab, 8, 2, None, dilate=1)
    assert samples.starts.tolist() == [
        2.0,
        2.5,
        3.0,
        3.5,
        4.0,
        4.5,
    ] and ratio.item() == pytest.approx(1 / 8)


def test_a_ray_with_nothing_kept_still_renders_its_foreground_with_the_fallback():
    near, far, origins, dirs = rays(8)
    samples, ratio = guided_samples(
        near,
        far,
        origins,
        dirs,
        nothing,
        8,
        4,
        Noise(torch.Generator().manual_seed(0)),
        fallback=True,
    )
    assert ratio.item() == 0.0
    # One sample per coarse bin on each of the 4 rays inside the box: 8, not 8 x split.
    assert samples.ray_index.tolist() == [r for r in range(4, 8) for _ in range(8)]
    check_invariants(samples, near, far)
    per_ray = torch.zeros(8).index_add_(0, samples.ray_index, samples.deltas)
    assert torch.allclose(per_ray[4:], (far - near)[4:])  # the whole segment is covered
    without, _ = guided_samples(near, far, origins, dirs, nothing, 8, 4, None)
    assert len(without) == 0  # the paper's sampler: background only


def test_empty_threshold_keeps_a_superset_of_the_top1_decision():
    from model.estimators.occupancy import OccupancyPredictor
    from model.fields.hmoe import OccupancyNetwork

    torch.manual_seed(0)
    network = OccupancyNetwork(num_scene_experts=4, width=16, xyz_frequencies=4)
    with torch.no_grad():
        network.output.bias[-1] = 1.5  # E_e wins on most points, as after phase 1
    xyz = torch.rand(4000, 3) * 2 - 1
    top1 = OccupancyPredictor(network).occupied(xyz)
    loose = OccupancyPredictor(network, empty_threshold=0.9).occupied(xyz)
    p_empty = torch.softmax(network(xyz), -1)[:, -1]
    assert torch.equal(loose, p_empty < 0.9)
    # every top-1 point kept, and more
    assert (loose | ~top1).all() and loose.sum() > top1.sum() > 0


class WallField(torch.nn.Module):
    """An analytic scene: an opaque red slab at x in SLAB, empty elsewhere (density 1e3 per unit
    length)."""

    def forward(self, xyz, dirs, image_index):
        from model.fields.output import FieldOutput

        sigma = wall(xyz).float() * 1e3
        rgb = torch.tensor([1.0, 0.0, 0.0]).expand(len(xyz), 3)
        n = len(xyz)
        return FieldOutput(
            sigma,
            rgb,
            torch.ones(n, 1),
            torch.zeros(n, dtype=torch.long),
            torch.ones(n, dtype=torch.bool),
        )


def straight_rays(n=16):
    from model.scenes.rays import RayBatch

    origins = torch.stack([torch.zeros(n), torch.linspace(-1, 1, n), torch.zeros(n)], -1)
    dirs = torch.tensor([[1.0, 0.0, 0.0]]).expand(n, 3).contiguous()
    return RayBatch(
        origins,
        dirs,
        torch.zeros(n),
        torch.full((n,), 8.0),
        torch.zeros(n, dtype=torch.long),
        torch.zeros(n, 3),
        torch.arange(n),
    )


def test_transmittance_culling_drops_only_samples_behind_an_opaque_wall():
    from model.methods.main_phase import composite_field, cull_occluded, field_on_packed

    rays, field = straight_rays(), WallField()
    samples, _ = guided_samples(
        rays.near,
        rays.far,
        rays.origins,
        rays.directions,
        KeepEverything().occupied,
        8,
        8,
        Noise(torch.Generator().manual_seed(0)),
    )
    culled = samples.subset(cull_occluded(field, rays, samples, 1e-3))
    check_invariants(culled, rays.near, rays.far)
    assert (culled.starts < SLAB[1]).all(), "nothing behind the wall survives"
    in_front = samples.ends <= SLAB[0]
    assert in_front.sum() > 0 and len(culled) >= int(in_front.sum()), (
        "every sample in front of the wall is kept"
    )
    assert len(culled) < 0.5 * len(samples)  # the wall is at x = 2 of 8: most samples are behind it
    behind = torch.zeros(len(rays), 3)
    full = composite_field(field_on_packed(field, rays, samples), rays, samples, behind).rgb
    cut = composite_field(field_on_packed(field, rays, culled), rays, culled, behind).rgb
    assert torch.allclose(full, cut, atol=1e-3)  # what culling removes was at most eps of light
    assert torch.allclose(full, torch.tensor([1.0, 0.0, 0.0]).expand_as(full), atol=1e-3)


def test_transmittance_culling_in_the_guided_render_counts_both_passes():
    from model.fields.background import BackgroundField
    from model.fields.switch_nerf import SwitchNeRF
    from model.methods.leco.guided_render import render_guided
    from model.profiles import get_profile

    torch.manual_seed(0)
    profile = get_profile("smoke")
    rays = straight_rays()
    field = SwitchNeRF(
        1,
        width=16,
        num_experts=2,
        expert_layers=2,
        xyz_frequencies=4,
        dir_frequencies=2,
        appearance_dim=4,
    )
    field.eval()  # no density noise: both renders see the same field
    with torch.no_grad():
        # opaque from the first samples: most of each ray is hidden
        field.head.sigma.bias.fill_(8.0)
    background = BackgroundField(
        1, width=8, layers=1, frequencies=2, dir_frequencies=2, appearance_dim=4
    )
    everything = KeepEverything()
    plain = render_guided(field, background, rays, profile, everything, None)
    culled_profile = profile.model_copy(
        update={"guided": profile.guided.model_copy(update={"cull_transmittance": 1e-4})}
    )
    culled = render_guided(field, background, rays, culled_profile, everything, None)
    assert torch.allclose(plain.rendered.rgb, culled.rendered.rgb, atol=1e-3)
    evaluated = plain.samples_per_ray  # every sample, once
    # all once without gradient, the visible again
    assert evaluated < culled.samples_per_ray < 2 * evaluated


def test_o_is_asked_about_the_rays_that_hit_the_box_only():
    near, far, origins, dirs = rays()
    far[: len(far) // 2] = near[: len(far) // 2]  # half the rays miss the box
    asked = []

    def counting(points):
        asked.append(len(points))
        return wall(points)

    for options in ({}, {"dilate": 1, "fallback": True}):
        samples, ratio = guided_samples(near, far, origins, dirs, counting, 8, 4, None, **options)
        assert asked[-1] == 32 * 8
        assert int(samples.ray_index.min()) >= 32
        assert 0 < float(ratio) < 1  # over the hit rays' bins only


def test_the_top_k_fallback_samples_the_bins_o_scores_highest():
    near, far, origins, dirs = rays()
    # every bin dropped; the last two score highest
    scores = torch.arange(8.0).repeat(len(near), 1) - 100.0
    samples, _ = guided_samples(
        near,
        far,
        origins,
        dirs,
        nothing,
        8,
        4,
        None,
        fallback=True,
        topk=2,
        scores=lambda: scores[4:].reshape(-1),
    )
    check_invariants(samples, near, far)
    hits = 60
    assert len(samples) == hits * 2 * 4  # two bins, each split in 4
    span = (far - near)[samples.ray_index]
    position = (samples.mids - near[samples.ray_index]) / span
    assert (position >= 6 / 8 - 1e-6).all()  # inside the last two coarse bins


def test_explored_bins_are_dropped_bins_drawn_at_random_while_training_only():
    near, far, origins, dirs = rays()
    # O keeps only the bin holding the wall (bin 2 of 8 on most rays)
    kept, _ = guided_samples(near, far, origins, dirs, wall, 8, 4, None)
    noise = Noise(torch.Generator().manual_seed(3))
    explored, _ = guided_samples(near, far, origins, dirs, wall, 8, 4, noise, explore=2)
    check_invariants(explored, near, far)
    per_ray = torch.bincount(explored.ray_index, minlength=len(near))
    before = torch.bincount(kept.ray_index, minlength=len(near))
    assert per_ray[:4].sum() == 0, "rays that miss the box get nothing"
    assert (per_ray[4:] == before[4:] + 2 * 4).all(), "two more bins a hit ray, split in 4"
    # over many steps every dropped bin of a ray is explored, none twice in one step
    seen = torch.zeros(8, dtype=torch.long)
    for _ in range(40):
        one, _ = guided_samples(
            near[4:5], far[4:5], origins[4:5], dirs[4:5], wall, 8, 1, noise, explore=2
        )
        bins = ((one.mids - near[4]) / (far[4] - near[4]) * 8).long()
        assert len(bins.unique()) == len(bins)
        seen[bins] += 1
    assert (seen > 0).all()
    # without noise (a validation render) nothing is explored
    assert guided_samples(near, far, origins, dirs, wall, 8, 4, None, explore=2)[0].starts.equal(
        kept.starts
    )

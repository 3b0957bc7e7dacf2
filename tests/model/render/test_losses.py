"""mip-NeRF 360's distortion loss in packed form against its double sum, and what it prefers."""

import torch

from model.render.losses import distortion_loss
from model.render.samples import PackedSamples
from model.render.volume import exclusive_cumsum_per_ray


def brute_force(weights, starts, ends, ray_index, near, far, num_rays):
    total = 0.0
    for r in range(num_rays):
        on = ray_index == r
        w = weights[on].double()
        length = float(far[r] - near[r])
        s0 = (starts[on].double() - near[r]) / length
        s1 = (ends[on].double() - near[r]) / length
        m = 0.5 * (s0 + s1)
        total += float((w[:, None] * w[None] * (m[:, None] - m[None]).abs()).sum())
        total += float((w**2 * (s1 - s0)).sum() / 3)
    return total / num_rays


def packed(counts, generator):
    """Random sorted intervals on rays with these sample counts (a ray may have none)."""
    starts, ends, index = [], [], []
    for r, n in enumerate(counts):
        edges = torch.sort(torch.rand(n + 1, generator=generator)).values * 3 + 1
        starts.append(edges[:-1])
        ends.append(edges[1:])
        index.append(torch.full((n,), r))
    return PackedSamples(torch.cat(starts), torch.cat(ends), torch.cat(index))


def test_the_packed_distortion_is_the_double_sum():
    g = torch.Generator().manual_seed(0)
    counts = [5, 0, 1, 9, 3]
    samples = packed(counts, g)
    weights = torch.rand(len(samples), generator=g) / 4
    near, far = torch.ones(5), torch.full((5,), 4.0)
    got = distortion_loss(weights, samples, near, far, 5)
    expected = brute_force(weights, samples.starts, samples.ends, samples.ray_index, near, far, 5)
    assert abs(float(got) - expected) < 1e-6 and expected > 0
    assert exclusive_cumsum_per_ray(torch.ones(len(samples)), samples.ray_index, 5).tolist() == [
        0,
        1,
        2,
        3,
        4,
        0,
        0,
        1,
        2,
        3,
        4,
        5,
        6,
        7,
        8,
        0,
        1,
        2,
    ]


def test_one_sharp_surface_costs_less_than_fog_of_the_same_opacity():
    edges = torch.linspace(1.0, 4.0, 11)
    samples = PackedSamples(edges[:-1], edges[1:], torch.zeros(10, dtype=torch.long))
    near, far = torch.ones(1), torch.full((1,), 4.0)
    surface = torch.zeros(10)
    surface[4] = 0.9
    fog = torch.full((10,), 0.09)
    sharp = distortion_loss(surface, samples, near, far, 1)
    spread = distortion_loss(fog, samples, near, far, 1)
    assert float(sharp) < 0.2 * float(spread)
    # its gradient pulls the fog in: the outermost samples lose weight fastest
    fog.requires_grad_(True)
    distortion_loss(fog, samples, near, far, 1).backward()
    assert fog.grad[0] > fog.grad[5] and fog.grad[9] > fog.grad[4]
    assert (
        float(
            distortion_loss(
                torch.zeros(0), samples.subset(torch.zeros(10, dtype=torch.bool)), near, far, 1
            )
        )
        == 0.0
    )

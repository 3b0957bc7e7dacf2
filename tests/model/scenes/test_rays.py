"""Ray generation, the seeded shuffling sampler, and the sharding rule."""

from dataclasses import replace

import pytest
import torch

from model.scenes import RaySampler, Views, shard
from model.scenes.bounds import ray_aabb
from model.scenes.cameras import make_cameras

AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def small_views(n=3, w=8, h=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    images = [torch.randint(0, 256, (h, w, 3), generator=g, dtype=torch.uint8) for _ in range(n)]
    c2w = torch.zeros(n, 3, 4)
    c2w[:, :, :3] = torch.eye(3)
    # narrow views down -z into the box
    c2w[:, :, 3] = torch.tensor([[0.0, 0.0, 3.0 + i] for i in range(n)])
    cams = make_cameras(
        torch.tensor([[4 * w, 4 * w, w / 2, h / 2]] * n, dtype=torch.float32),
        c2w,
        torch.full((n,), w),
        torch.full((n,), h),
    )
    return Views([f"{i}" for i in range(n)], images, cams, torch.arange(n) + 10)


def test_shard_disjoint_equal_and_covering():
    batch = torch.randperm(96, generator=torch.Generator().manual_seed(1))
    for world in (1, 2, 3, 4, 8):
        parts = [shard(batch, r, world) for r in range(world)]
        assert {len(p) for p in parts} == {96 // world}
        joined = torch.cat(parts)
        assert torch.equal(joined, batch)  # covers the batch, in order
        assert len(joined.unique()) == 96  # disjoint


def test_shard_refuses_uneven_split():
    with pytest.raises(ValueError, match="does not split evenly over 5 ranks"):
        shard(torch.arange(96), 0, 5)
    with pytest.raises(ValueError, match="rank must be in"):
        shard(torch.arange(96), 4, 4)


def test_sampler_epoch_is_a_permutation_and_seeded():
    views = small_views()
    sampler = RaySampler(views, AABB, batch_size=16, seed=7)
    n = views.num_pixels  # 144 -> 9 batches per epoch
    seen = torch.cat([sampler.next_global() for _ in range(sampler.batches_per_epoch)])
    assert sorted(seen.tolist()) == list(range(n))
    again = RaySampler(views, AABB, batch_size=16, seed=7)
    assert torch.equal(again.next_global(), seen[:16])
    other = RaySampler(views, AABB, batch_size=16, seed=8)
    assert not torch.equal(other.next_global(), seen[:16])
    # The next epoch is a different permutation.
    assert not torch.equal(sampler.next_global(), seen[:16])


def test_sampler_ranks_share_each_global_batch():
    views = small_views()
    ranks = [RaySampler(views, AABB, batch_size=24, seed=3, rank=r, world_size=4) for r in range(4)]
    reference = RaySampler(views, AABB, batch_size=24, seed=3)
    for _ in range(7):  # crosses an epoch boundary (6 batches of 24 per epoch of 144 pixels)
        parts = [s.next().pixel for s in ranks]
        assert torch.equal(torch.cat(parts), reference.next_global())
        assert all(len(p) == 6 for p in parts)


def test_sampler_resumes_from_state():
    views = small_views()
    a = RaySampler(views, AABB, batch_size=16, seed=5)
    for _ in range(11):
        a.next_global()
    state = a.state_dict()
    b = RaySampler(views, AABB, batch_size=16, seed=5)
    b.load_state_dict(state)
    assert torch.equal(a.next_global(), b.next_global())
    with pytest.raises(ValueError, match="sampler state is for seed=5"):
        RaySampler(views, AABB, batch_size=16, seed=6).load_state_dict(state)


@pytest.mark.parametrize("kept", [True, False])
def test_a_kept_epoch_order_gives_the_batches_the_evaluated_permutation_gives(monkeypatch, kept):
    import model.scenes.rays as rays_module

    views = small_views()  # 144 pixels
    evaluated = RaySampler(views, AABB, batch_size=16, seed=4)
    monkeypatch.setattr(rays_module, "KEPT_ORDER_MAX_PIXELS", 0)  # too large to keep: evaluated
    reference = [evaluated.next_global() for _ in range(20)]  # two epochs and more
    assert evaluated._order is None
    monkeypatch.setattr(rays_module, "KEPT_ORDER_MAX_PIXELS", 144 if kept else 143)
    monkeypatch.setattr(rays_module, "ORDER_CHUNK", 50)  # built in three chunks
    sampler = RaySampler(views, AABB, batch_size=16, seed=4)
    for k, batch in enumerate(reference):
        assert torch.equal(sampler.next_global(), batch), k
        assert batch.dtype == torch.int64
    assert (sampler._order is not None) == kept
    # a resume lands on the same order, mid-epoch
    resumed = RaySampler(views, AABB, batch_size=16, seed=4)
    resumed.load_state_dict({**sampler.state_dict()})
    assert torch.equal(resumed.next_global(), sampler.next_global())


def test_ray_batch_contents():
    views = small_views()
    sampler = RaySampler(views, AABB, batch_size=32, seed=0)
    rays = sampler.next()
    assert torch.allclose(rays.directions.norm(dim=-1), torch.ones(32), atol=1e-6)
    image, u, v = sampler.table.locate(rays.pixel)
    for k in range(32):
        expected = views.images[image[k]][v[k], u[k]].float() / 255
        assert torch.equal(rays.rgb[k], expected)
    assert torch.equal(rays.image_index, views.appearance[image])
    # Cameras above the box looking down: every ray enters at z = 1 and leaves through the box.
    assert (rays.far > rays.near).all()
    entry = rays.origins + rays.near[:, None] * rays.directions
    assert torch.allclose(entry[:, 2], torch.ones(32), atol=1e-5)


def test_ray_aabb_cases():
    origins = torch.tensor([[0.0, 0.0, 5.0], [0.0, 0.0, 0.0], [3.0, 3.0, 5.0], [0.5, -5.0, 0.5]])
    dirs = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    near, far = ray_aabb(origins, dirs, AABB)
    # outside, inside (starts at 0), miss, axis-parallel
    assert near.tolist() == [4.0, 0.0, 0.0, 4.0]
    assert far.tolist() == [6.0, 1.0, 0.0, 6.0]
    assert torch.isfinite(near).all() and torch.isfinite(far).all()


def test_a_resident_sampler_makes_the_host_samplers_batches(monkeypatch):
    """A GPU run's sampler keeps colours, cameras and each epoch's order on its device; on the CPU
    (`resident=True`) it must make the very batches the host sampler makes, past an epoch's end
    and for a split too large for the host to keep its order, and resume to the same batch."""
    import model.scenes.rays as rays_module

    monkeypatch.setattr(rays_module, "KEPT_ORDER_MAX_PIXELS", 0)  # the host evaluates each batch
    views = small_views()
    host = RaySampler(views, AABB, batch_size=16, seed=2)
    resident = RaySampler(views, AABB, batch_size=16, seed=2, resident=True)
    assert resident.table._colours is not None and resident.table._colours.dtype == torch.uint8
    for k in range(12):  # 9 batches an epoch
        a, b = host.next(), resident.next()
        for name, value in a.__dict__.items():
            assert torch.equal(value, getattr(b, name)), (k, name)
    assert host._order is None and resident._order is not None
    again = RaySampler(views, AABB, batch_size=16, seed=2, resident=True)
    again.load_state_dict(resident.state_dict())
    assert torch.equal(again.next().rgb, host.next().rgb)


def test_a_distorted_camera_is_undistorted_in_every_batch_it_is_in():
    """The table decides once whether any camera is distorted; a batch is undistorted exactly as
    the per-batch check undistorted it (zeros leave a pinhole camera's rays unchanged)."""
    from model.scenes.cameras import pixel_rays

    views = small_views()
    k = torch.zeros(3, 4)
    k[1] = torch.tensor([0.5, -0.1, 0.01, 0.02])
    views = Views(views.names, views.images, replace(views.cameras, distortion=k), views.appearance)
    sampler = RaySampler(views, AABB, batch_size=48, seed=1)
    assert sampler.table.distorted
    rays = sampler.next()
    image, u, v = sampler.table.locate(rays.pixel)
    pinhole = replace(views.cameras, distortion=torch.zeros(3, 4))
    for i in range(3):
        at = image == i
        assert at.sum() > 5, i
        origins, directions = pixel_rays(views.cameras, image[at], u[at], v[at])
        assert torch.allclose(directions, rays.directions[at], atol=1e-7), i
        assert torch.equal(origins, rays.origins[at]), i
        _, undistorted = pixel_rays(pinhole, image[at], u[at], v[at])
        moved = (undistorted - rays.directions[at]).abs().max()
        assert (moved > 1e-4) if i == 1 else (moved < 1e-7), i

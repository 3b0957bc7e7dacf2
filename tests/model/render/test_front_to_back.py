"""Early ray termination for image renders: the samples it skips lie behind transmittance < eps, so
the image moves by less than eps, and on opaque rays it runs far fewer samples."""

import torch

from model.fields.output import FieldOutput
from model.render.front_to_back import front_to_back, rank_along_ray
from model.render.samples import PackedSamples
from model.render.volume import composite_packed


def wall_scene(num_rays: int = 64, per_ray: int = 200, seed: int = 0):
    """Rays along t in [0, 2) with a wall of density 30 from t = 1 on (opaque after ~0.3) and a
    thin haze in front; the colour varies along t so a wrong order or a lost sample shows."""
    g = torch.Generator().manual_seed(seed)
    counts = torch.randint(per_ray // 2, per_ray + 1, (num_rays,), generator=g)
    counts[0] = 0  # a ray the grid culled entirely
    ray_index = torch.repeat_interleave(torch.arange(num_rays), counts)
    rank = rank_along_ray(ray_index, num_rays)
    step = 2.0 / counts.clamp(min=1).float()
    starts = rank.float() * step[ray_index]
    ends = starts + step[ray_index]
    samples = PackedSamples(starts, ends, ray_index)
    calls: list[int] = []

    def field_on(index: torch.Tensor) -> FieldOutput:
        calls.append(len(index))
        t = samples.mids[index]
        sigma = torch.where(t >= 1.0, torch.full_like(t, 30.0), torch.full_like(t, 0.05))
        rgb = torch.stack([t / 2, 1 - t / 2, (t * 7).sin().abs()], -1)
        return one_expert(sigma, rgb)

    return samples, field_on, calls


def one_expert(sigma: torch.Tensor, rgb: torch.Tensor) -> FieldOutput:
    n = len(sigma)
    ones = torch.ones(n, dtype=torch.bool)
    return FieldOutput(sigma, rgb, torch.ones(n, 1), torch.zeros(n, dtype=torch.long), ones)


def image(out: FieldOutput | None, samples: PackedSamples, num_rays: int) -> torch.Tensor:
    assert out is not None
    behind = torch.tensor([0.2, 0.4, 0.6])
    return composite_packed(
        out.sigma, out.rgb, samples.mids, samples.deltas, samples.ray_index, num_rays, behind
    ).rgb


def test_rank_along_ray_counts_from_each_rays_first_sample():
    ray_index = torch.tensor([0, 0, 0, 2, 2, 3])
    assert rank_along_ray(ray_index, 5).tolist() == [0, 1, 2, 0, 1, 0]


def test_early_stop_moves_the_image_by_less_than_eps_and_runs_far_fewer_samples():
    samples, field_on, calls = wall_scene()
    full_out, full_samples = front_to_back(field_on, samples, 64, eps=0.0)
    full_calls = sum(calls)
    calls.clear()
    out, kept = front_to_back(field_on, samples, 64, eps=1e-4, block=8)
    assert full_calls == len(samples)
    # the wall is opaque ~0.3 past t = 1: about 65% of each ray's samples, not 100%
    assert 0.55 * len(samples) < sum(calls) < 0.75 * len(samples)
    assert len(kept) == sum(calls)
    # the samples that ran are packed again: grouped by ray, increasing t
    assert torch.all(kept.ray_index[1:] >= kept.ray_index[:-1])
    same_ray = kept.ray_index[1:] == kept.ray_index[:-1]
    assert torch.all(kept.starts[1:][same_ray] > kept.starts[:-1][same_ray])
    gap = (image(out, kept, 64) - image(full_out, full_samples, 64)).abs().max()
    assert 0 < gap < 1e-4
    # eps = 0 runs every sample, as training does
    assert len(full_samples) == len(samples)


def test_early_stop_keeps_gradients_for_appearance_fitting():
    samples, _, _ = wall_scene(num_rays=8, per_ray=40)
    tint = torch.zeros(3, requires_grad=True)

    def field_on(index: torch.Tensor) -> FieldOutput:
        t = samples.mids[index]
        sigma = torch.where(t >= 1.0, 30.0, 0.05) * torch.ones_like(t)
        return one_expert(sigma, torch.sigmoid(tint).expand(len(index), 3))

    out, kept = front_to_back(field_on, samples, 8, eps=1e-4, block=4)
    image(out, kept, 8).sum().backward()
    assert tint.grad is not None and float(tint.grad.abs().sum()) > 0

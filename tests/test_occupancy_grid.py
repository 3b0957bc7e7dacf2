"""The occupancy-grid baseline follows nerfacc's OccGridEstimator update and sampling rules."""

import torch

from model.occupancy_grid import GridEstimator, cull_by_transmittance

AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def ball(points):
    """Density 100 inside a ball of radius 0.5, 0 outside."""
    return (points.norm(dim=-1) < 0.5).float() * 100.0


def test_warmup_queries_every_cell_then_a_quarter_plus_occupied():
    grid = GridEstimator(AABB, resolution=16)
    g = torch.Generator().manual_seed(0)
    assert grid.update(0, ball, step_size=0.01, generator=g) and grid.queries == 16**3
    assert not grid.update(5, ball, step_size=0.01, generator=g)  # only every 16 steps
    occupied_cells = int(grid.binary.sum())
    grid.update(256, ball, step_size=0.01, generator=g)  # after warm-up
    assert grid.queries == 16**3 + 16**3 // 4 + min(occupied_cells, 16**3 // 4)
    centre = torch.zeros(1, 3)
    corner = torch.tensor([[0.95, 0.95, 0.95]])
    assert grid.occupied(centre).item() and not grid.occupied(corner).item()
    assert not grid.occupied(torch.tensor([[2.0, 0.0, 0.0]])).item()  # outside the box: free


def test_decay_max_and_threshold_rule():
    grid = GridEstimator(AABB, resolution=8)
    grid.update(0, lambda p: torch.full((len(p),), 2.0), step_size=0.01)  # value 0.02 everywhere
    assert torch.allclose(grid.values, torch.full((512,), 0.02))
    grid.update(16, lambda p: torch.zeros(len(p)), step_size=0.01)  # decays, max keeps the old
    assert torch.allclose(grid.values, torch.full((512,), 0.019))
    # Threshold is min(mean, 0.01): a uniform grid above 0.01 is all occupied.
    assert grid.binary.all()


def test_sampling_keeps_only_occupied_cells_and_culling_drops_hidden_samples():
    grid = GridEstimator(AABB, resolution=32)
    grid.update(0, ball, step_size=0.01)
    origins = torch.tensor([[-2.0, 0.0, 0.0], [-2.0, 0.9, 0.9]])
    dirs = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    near, far = torch.tensor([1.0, 1.0]), torch.tensor([3.0, 3.0])
    samples = grid.sample(origins, dirs, near, far, step_size=0.02)
    assert set(samples.ray_index.tolist()) == {0}  # the second ray passes outside the ball
    x = origins[0, 0] + samples.mids
    assert (x.abs() < 0.5 + 2 * (2.0 / 32)).all() and len(samples) > 30
    culled = cull_by_transmittance(
        samples, ball(torch.stack([x, torch.zeros_like(x), torch.zeros_like(x)], -1)), 2
    )
    # everything behind the opaque front of the ball is dropped
    assert 0 < len(culled) < len(samples)

"""The occupancy-grid baseline follows nerfacc's OccGridEstimator update and sampling rules."""

import torch

from model.estimators.grid import GridEstimator, cull_by_transmittance
from model.render.noise import Noise

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


def shell(points):
    """Density 100 between 2.5 and 3.5 from the centre (max norm), 0 elsewhere: far outside the
    box."""
    reach = points.abs().amax(-1)
    return ((reach > 2.5) & (reach < 3.5)).float() * 100.0


def test_one_level_indexes_cells_as_the_single_box_grid_did():
    grid = GridEstimator(AABB, resolution=16)
    points = torch.rand(4096, 3, generator=torch.Generator().manual_seed(1)) * 3 - 1.5
    index, inside = grid._cell_index(points)
    ijk = torch.floor((points - AABB[0]) / (AABB[1] - AABB[0]) * 16).long()
    expected_inside = ((ijk >= 0) & (ijk < 16)).all(-1)
    ijk = ijk.clamp(0, 15)
    assert torch.equal(inside, expected_inside)
    assert torch.equal(index, (ijk[:, 0] * 16 + ijk[:, 1]) * 16 + ijk[:, 2])


def test_cascades_cover_points_far_outside_the_box():
    grid = GridEstimator(AABB, resolution=16, levels=3)  # reaches 4x the box's half-extent
    grid.update(0, shell, step_size=0.01, generator=torch.Generator().manual_seed(0))
    assert grid.queries == 3 * 16**3  # warm-up: every cell of every level
    far_in_shell = torch.tensor([[3.0, 0.2, -0.4], [-0.3, -3.1, 1.0]])
    between = torch.tensor([[1.7, 0.0, 0.0], [0.0, 0.0, -2.0]])
    beyond = torch.tensor([[5.0, 0.0, 0.0], [0.0, 9.0, 0.0]])
    assert grid.occupied(far_in_shell).all() and not grid.occupied(between).any()
    assert not grid.occupied(beyond).any() and grid.beyond(beyond).all()
    assert not grid.beyond(far_in_shell).any() and not grid.beyond(torch.zeros(1, 3)).any()
    everywhere = torch.cat([far_in_shell, between, beyond])
    assert torch.equal(
        grid.not_free(everywhere), grid.occupied(everywhere) | grid.beyond(everywhere)
    )
    # the finest level that holds a point decides: level 1's cell at (1.7, 0, 0) is 0.25 wide
    index, _ = grid._cell_index(torch.tensor([[1.7, 0.0, 0.0], [3.0, 0.0, 0.0]]))
    assert (index // 16**3).tolist() == [1, 2]


def test_cascaded_update_points_reach_the_outer_level():
    grid = GridEstimator(AABB, resolution=8, levels=4)
    seen = []
    grid.update(0, lambda p: seen.append(p) or torch.zeros(len(p)), step_size=0.01)
    points = torch.cat(seen)
    reach = points.abs().amax(-1)
    assert len(points) == 4 * 8**3 and reach.max() > 7.0 and reach.max() <= 8.0
    # each level's points are spread over its whole box, inner region included
    assert (reach <= 1.0).sum() >= 8**3


def test_cascaded_background_render_drops_only_free_samples():
    from model.fields.background import BackgroundField
    from model.methods.leco.phase1 import render_background
    from model.methods.main_phase import render_background_cascaded
    from model.scenes.rays import RayBatch

    torch.manual_seed(0)
    background = BackgroundField(1, width=16, layers=1, appearance_dim=4).eval()
    n = 64
    directions = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1)
    rays = RayBatch(
        origins=torch.zeros(n, 3),
        directions=directions,
        near=torch.zeros(n),
        far=torch.full((n,), 1.0),
        image_index=torch.zeros(n, dtype=torch.long),
        rgb=torch.zeros(n, 3),
        pixel=torch.arange(n),
    )
    grid = GridEstimator(AABB, resolution=8, levels=3)  # unupdated: every cell may be occupied
    with torch.no_grad():
        full = render_background(background, rays, 32, None).rgb
        cascaded, kept = render_background_cascaded(background, rays, 32, grid, None)
        assert kept == 1.0 and torch.allclose(cascaded, full, atol=1e-6)
        grid.binary[:] = False  # the cascades say nothing is there: only samples beyond them stay
        culled, kept = render_background_cascaded(background, rays, 32, grid, None)
    t = 1.0 / (1.0 - (torch.arange(32) + 0.5) / 32)  # the background's samples from far = 1
    beyond = grid.beyond((directions[:, None] * t[:, None]).reshape(-1, 3)).float().mean()
    assert 0 < kept < 1 and abs(kept - float(beyond)) < 1e-6
    assert not torch.allclose(culled, full)


def masked_cell_index(grid, points):
    """The cascaded cell lookup as it was written with masks (a gather per tensor): the reference
    the mask-free lookup must equal."""
    r = grid.resolution
    unit = (points - grid.aabb[0]) / (grid.aabb[1] - grid.aabb[0])
    ijk = torch.floor(unit * r).long()
    inside = ((ijk >= 0) & (ijk < r)).all(-1)
    level = torch.zeros(len(points), dtype=torch.long)
    outer = ~inside
    centre, half = grid.aabb.mean(0), (grid.aabb[1] - grid.aabb[0]) / 2
    reach = ((points[outer] - centre) / half).abs().amax(-1)
    level[outer] = torch.ceil(torch.log2(reach.clamp(min=1.0))).long().clamp(min=1)
    lo, hi = grid.level_box(level[outer])
    ijk[outer] = torch.floor((points[outer] - lo) / (hi - lo) * r).long()
    inside[outer] = ((ijk[outer] >= 0) & (ijk[outer] < r)).all(-1) & (level[outer] < grid.levels)
    ijk, level = ijk.clamp(0, r - 1), level.clamp(max=grid.levels - 1)
    return ((level * r + ijk[:, 0]) * r + ijk[:, 1]) * r + ijk[:, 2], inside


def test_the_cascaded_lookup_without_masks_equals_the_masked_one():
    grid = GridEstimator(AABB, resolution=16, levels=3)
    g = torch.Generator().manual_seed(0)
    # inside the box, in each outer level, past the outermost, and on the levels' faces
    points = torch.cat(
        [
            torch.rand(500, 3, generator=g) * 2 - 1,
            (torch.rand(2000, 3, generator=g) * 2 - 1) * 6,
            torch.tensor([[1.0, 0.0, 0.0], [2.0, -2.0, 0.5], [4.0, 0.0, 0.0], [-1.0, -1.0, -1.0]]),
        ]
    )
    index, inside = grid._cell_index(points)
    expected_index, expected_inside = masked_cell_index(grid, points)
    assert torch.equal(inside, expected_inside) and 0 < int(inside.sum()) < len(points)
    assert torch.equal(index, expected_index)


def test_a_march_bounded_by_the_diagonal_keeps_the_samples_the_read_length_gives():
    grid = GridEstimator(AABB, resolution=32)
    grid.update(0, ball, step_size=0.01)
    g = torch.Generator().manual_seed(3)
    directions = torch.nn.functional.normalize(torch.randn(64, 3, generator=g), dim=-1)
    directions[0] = torch.tensor([1.0, 1.0, 1.0]) / 3**0.5  # through the box along its diagonal
    origins = -3 * directions + 0.2 * torch.randn(64, 3, generator=g)
    origins[0] = torch.tensor([-2.0, -2.0, -2.0])
    from model.scenes.bounds import ray_aabb

    near, far = ray_aabb(origins, directions, AABB)
    assert (far - near).max() > 0.999 * grid.diagonal
    for seed in (None, 5):

        def draw(seed=seed):
            return Noise(torch.Generator().manual_seed(seed)) if seed is not None else None

        read = grid.sample(origins, directions, near, far, 0.02, draw())
        bounded = grid.sample(origins, directions, near, far, 0.02, draw(), grid.diagonal)
        assert len(read) > 100
        for name in ("starts", "ends", "ray_index"):
            assert torch.equal(getattr(read, name), getattr(bounded, name)), (seed, name)

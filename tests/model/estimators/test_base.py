"""Adding an estimator is one file: a subclass of Estimator that answers `occupied`. The toy below
is marched by the base class's `sample` and scored by the paper's occupancy protocol exactly like
the grid and O, with nothing else written for it."""

import torch

from model.estimators.base import Estimator
from model.estimators.grid import GridEstimator
from model.evaluation.occupancy import evaluate_occupancy_exact
from model.render.noise import Noise


class BelowPlane(Estimator):
    """Toy: everything under z = height is occupied."""

    def __init__(self, height: float):
        self.height = height

    def occupied(self, points: torch.Tensor) -> torch.Tensor:
        return points[:, 2] < self.height


def test_a_toy_estimator_is_marched_only_where_it_says_occupied():
    origins = torch.tensor([[0.0, 0.0, 1.0], [0.5, 0.5, 1.0]])
    directions = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    near, far = torch.zeros(2), torch.full((2,), 2.0)
    samples = BelowPlane(0.0).sample(origins, directions, near, far, step_size=0.25)
    z = 1.0 - samples.mids
    # each ray crosses z < 0 over t in (1, 2]: 4 intervals of 0.25, mid-points below the plane
    assert samples.ray_index.tolist() == [0] * 4 + [1] * 4
    assert torch.allclose(z, torch.tensor([-0.125, -0.375, -0.625, -0.875] * 2))
    jittered = BelowPlane(0.0).sample(
        origins, directions, near, far, 0.25, Noise(torch.Generator().manual_seed(0))
    )
    # one random offset a ray: ray 1 starts late enough for a fifth mid-point below the plane
    assert ((1.0 - jittered.mids) < 0).all() and jittered.ray_index.tolist() == [0] * 4 + [1] * 5


def test_the_grid_marches_through_the_same_base_class():
    grid = GridEstimator(torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), resolution=4)
    grid.binary[:] = False
    assert isinstance(grid, Estimator)
    samples = grid.sample(
        torch.zeros(1, 3), torch.tensor([[1.0, 0.0, 0.0]]), torch.zeros(1), torch.ones(1), 0.1
    )
    assert len(samples) == 0


def test_a_toy_estimator_is_scored_by_the_occupancy_protocol(tiny_scene):
    views = tiny_scene.splits.get("val", tiny_scene.train)
    truth = tiny_scene.occupancy
    everything = evaluate_occupancy_exact(BelowPlane(1e9).occupied, truth, views, 32)
    nothing = evaluate_occupancy_exact(BelowPlane(-1e9).occupied, truth, views, 32)
    assert everything["recall"] == 1.0 and 0 < everything["precision"] < 1
    assert nothing["recall"] == 0.0 and nothing["accuracy"] == 1 - everything["precision"]

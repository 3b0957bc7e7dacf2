"""The paper's occupancy protocol: reference from depth maps, predictor sampled into the same
grid."""

import pytest
import torch

from model.evaluation.occupancy import (
    cell_index,
    evaluate_occupancy,
    predicted_grid,
    reference_from_depth,
)


def test_cell_index_and_outside_points():
    aabb = torch.tensor([[0.0, 0.0, 0.0], [2.0, 2.0, 2.0]])
    index, inside = cell_index(
        torch.tensor([[0.1, 0.1, 0.1], [1.9, 0.1, 1.1], [2.0, 0.5, 0.5]]), aabb, 2
    )
    assert index[:2].tolist() == [0, 4 + 1] and inside.tolist() == [True, True, False]


def test_predicted_grid_samples_every_cell():
    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    grid = predicted_grid(lambda p: p[:, 2] > 0.5, aabb, 8)  # occupied above z = 0.5
    assert grid.shape == (8, 8, 8)
    assert grid[:, :, 6:].all() and not grid[:, :, :6].any()  # cell 6 starts at z = 0.5


def test_reference_and_protocol_on_the_exact_city(tiny_scene):
    views, aabb = tiny_scene.splits["val"], tiny_scene.occupancy.aabb
    occupied, observed = reference_from_depth(views, aabb, 64)
    assert occupied.any() and (observed & ~occupied).any() and not (occupied & ~observed).any()
    assert 0.1 < observed.float().mean() < 0.9  # drone views leave building interiors unseen
    grid = occupied.reshape(-1)
    from_reference = lambda p: grid[cell_index(p, aabb, 64)[0]]
    assert evaluate_occupancy(from_reference, views, aabb, 64)["f1"] == 1.0
    truth = evaluate_occupancy(tiny_scene.occupancy.lookup, views, aabb, 64)
    nothing = evaluate_occupancy(lambda p: torch.zeros(len(p), dtype=torch.bool), views, aabb, 64)
    everything = evaluate_occupancy(lambda p: torch.ones(len(p), dtype=torch.bool), views, aabb, 64)
    print(f"exact occupancy: {truth}\nall occupied: {everything}")
    # The exact solid also fills cells behind the surface that a depth map marks free only at its
    # edges.
    assert truth["recall"] > 0.95 and truth["precision"] > 0.45 and truth["accuracy"] > 0.98
    assert nothing["recall"] == 0.0 and nothing["accuracy"] == pytest.approx(
        1 - nothing["reference_occupied_fraction"]
    )
    assert everything["recall"] == 1.0 and everything["precision"] == pytest.approx(
        everything["reference_occupied_fraction"]
    )
    assert truth["f1"] > everything["f1"] + 0.5


def test_reference_needs_depth(tiny_scene):
    from dataclasses import replace

    views = replace(tiny_scene.splits["val"], depth=None)
    with pytest.raises(ValueError, match="needs depth maps"):
        reference_from_depth(views, tiny_scene.bounds.aabb, 8)

"""Occupancy by height layer and of the ground, and other decision rules scored on the same
reference."""

import pytest
import torch

import model.evaluation.occupancy as occupancy_eval
from model.evaluation.occupancy import (
    evaluate_occupancy,
    evaluate_occupancy_exact,
    ground_cells,
    layer_bounds,
    predicted_grid,
    score_grid,
    score_rules,
)

R = 16  # a hand-made 16^3 grid: 8 layers of 2 cells


def town() -> tuple[torch.Tensor, torch.Tensor]:
    """Ground at z = 0 in every column and a 4x4 tower from z = 1 to z = 12 on it; every cell
    observed."""
    reference = torch.zeros(R, R, R, dtype=torch.bool)
    reference[:, :, 0] = True
    reference[4:8, 4:8, 1:13] = True
    return reference, torch.ones_like(reference)


def test_layer_bounds_split_the_z_axis_evenly():
    assert layer_bounds(64) == [(8 * i, 8 * i + 8) for i in range(8)]
    assert (
        layer_bounds(16)[0] == (0, 2)
        and len(layer_bounds(20)) == 8
        and layer_bounds(20)[-1][1] == 20
    )


def test_a_predictor_that_drops_the_lowest_layer_loses_the_ground_and_only_it():
    reference, observed = town()
    predicted = reference.clone()
    predicted[:, :, :2] = False  # the lowest layer (z cells 0 and 1)
    scores = score_grid(predicted, reference, observed)
    assert scores["ground_cells"] == R * R and scores["ground_recall"] == 0.0
    recalls = [layer["recall"] for layer in scores["layers"]]
    assert recalls == [0.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, None]  # nothing stands in the top layer
    assert [layer["reference_cells"] for layer in scores["layers"]] == [
        R * R + 16,
        32,
        32,
        32,
        32,
        32,
        16,
        0,
    ]
    assert scores["layers"][0] == {
        "z_min": 0.0,
        "z_max": 0.125,
        "reference_cells": 272,
        "predicted_cells": 0,
        "recall": 0.0,
    }
    assert scores["layers"][7]["z_min"] == 0.875 and scores["layers"][7]["z_max"] == 1.0
    # The total barely shows it: 272 of 448 occupied cells dropped, and precision stays perfect.
    assert scores["recall"] == pytest.approx(176 / 448) and scores["precision"] == 1.0


def test_a_predictor_that_keeps_only_the_ground_scores_ground_recall_one():
    reference, observed = town()
    scores = score_grid(reference & (torch.arange(R) == 0), reference, observed)
    assert scores["ground_recall"] == 1.0 and scores["layers"][0]["recall"] == 256 / 272
    assert all(layer["recall"] in (0.0, None) for layer in scores["layers"][1:])


def test_the_ground_is_each_columns_lowest_observed_occupied_cell():
    reference, observed = town()
    observed[4:8, 4:8, :12] = False  # the tower's inside and the ground under it: seen by no view
    ground = ground_cells(reference, observed)
    assert int(ground.sum()) == R * R  # one per column
    assert ground[0, 0, 0] and ground[5, 5, 12] and not ground[5, 5, 0]  # under the tower: its roof
    empty = torch.zeros_like(reference)
    # no reference: no recall, not 0
    assert score_grid(empty, empty, observed)["ground_recall"] is None


def test_decision_rules_are_prefixed_and_scored_on_the_same_reference():
    reference, observed = town()
    aabb = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    keep_all = lambda p: torch.ones(len(p), dtype=torch.bool)
    above_ground = lambda p: p[:, 2] >= 2 / R
    scores = score_rules({"all": keep_all, "upper": above_ground}, reference, observed, aabb, R)
    assert set(scores) == {
        f"{rule}_{key}"
        for rule in ("all", "upper")
        for key in ("recall", "precision", "f1", "ground_recall")
    }
    assert scores["all_recall"] == 1.0 and scores["all_ground_recall"] == 1.0
    assert scores["all_precision"] == pytest.approx(448 / R**3)
    assert (
        scores["upper_recall"] == pytest.approx(176 / 448) and scores["upper_ground_recall"] == 0.0
    )
    assert score_rules(None, reference, observed, aabb, R) == {}


def test_the_exact_protocol_reports_layers_ground_and_rules_on_the_tiny_city(
    tiny_scene, monkeypatch
):
    truth, views = tiny_scene.occupancy, tiny_scene.splits["val"]
    calls = []
    reference_from_depth = occupancy_eval.reference_from_depth
    monkeypatch.setattr(
        occupancy_eval,
        "reference_from_depth",
        lambda *a, **k: calls.append(1) or reference_from_depth(*a, **k),
    )
    aabb = truth.aabb.float()
    cut = float(aabb[0, 2] + (aabb[1, 2] - aabb[0, 2]) / 8)  # the top of the lowest layer
    no_lowest_layer = lambda p: truth.lookup(p) & (p[:, 2] >= cut)
    scores = evaluate_occupancy_exact(
        truth.lookup, truth, views, 64, rules={"dropped": no_lowest_layer}
    )
    assert len(calls) == 1  # the rules reuse the reference (its depth marching is the slow part)
    assert (
        scores["recall"] == 1.0
        and scores["ground_recall"] == 1.0
        and scores["dropped_recall"] < 0.6
    )
    assert [layer["recall"] for layer in scores["layers"]] == [1.0] * 8
    assert (
        sum(layer["reference_cells"] for layer in scores["layers"]) > scores["ground_cells"] > 500
    )
    dropped = score_grid(
        predicted_grid(no_lowest_layer, aabb, 64),
        predicted_grid(truth.lookup, aabb, 64),
        occupancy_eval.reference_from_depth(views, aabb, 64)[1],
    )
    assert [layer["recall"] for layer in dropped["layers"]] == [0.0] + [1.0] * 7
    # the rest: roofs no view sees under
    assert dropped["ground_recall"] == scores["dropped_ground_recall"] < 0.3
    for key in (
        "accuracy",
        "precision",
        "recall",
        "f1",
        "whole_grid_f1",
        "observed_fraction",
        "resolution",
    ):
        assert key in scores  # the keys from before are all still there


def test_the_depth_protocol_reports_the_same_keys(tiny_scene):
    views, aabb = tiny_scene.splits["val"], tiny_scene.occupancy.aabb
    scores = evaluate_occupancy(
        tiny_scene.occupancy.lookup,
        views,
        aabb,
        64,
        rules={"none": lambda p: torch.zeros(len(p), dtype=torch.bool)},
    )
    assert (
        len(scores["layers"]) == 8 and scores["ground_cells"] > 0 and scores["ground_recall"] > 0.9
    )
    assert scores["none_recall"] == 0.0 and scores["none_ground_recall"] == 0.0

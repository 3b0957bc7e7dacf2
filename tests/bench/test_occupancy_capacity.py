"""The capacity diagnostic fits O straight to an occupancy: on a toy (a small tower in an empty box)
the fit learns to keep the tower and drop the air, and on the tiny city it writes one scored row
per checkpoint, as a finished run's O is scored."""

import json

import torch

from bench.occupancy_capacity import CHECKPOINTS, fit, main
from model.fields.hmoe import OccupancyNetwork


def test_the_fit_keeps_a_small_tower_and_drops_the_air_around_it():
    torch.manual_seed(0)
    points = torch.rand(20_000, 3) * 2 - 1
    # a tower 0.2 wide and 1.2 tall: 1.2% of the box, as thin a thing as a silo
    labels = (points[:, :2].abs() < 0.1).all(-1) & (points[:, 2] < 0.2)
    network = OccupancyNetwork(num_scene_experts=2, width=32, xyz_frequencies=4)
    before = network.occupied(points, 0.9)
    fit(network, points, labels, 300, 1024, 5e-3, 0.9, seed=0, report=lambda step: None)
    kept = network.occupied(points, 0.9)
    recall = float((kept & labels).sum() / labels.sum())
    precision = float((kept & labels).sum() / kept.sum().clamp(min=1))
    assert recall > 0.9 and precision > 0.5, (recall, precision)
    assert not torch.equal(before, kept)


def test_it_scores_the_fitted_o_of_a_scene_at_each_checkpoint(tmp_path, capsys):
    from model.scenes.synthetic import generate

    scene = tmp_path / "tiny-0"
    generate("tiny", 0, scene)
    out = tmp_path / "rows.json"
    args = ["--scene", str(scene), "--profile", "smoke", "--steps", "40", "--batch", "256"]
    assert main([*args, "--json", str(out)]) == 0
    rows = json.loads(out.read_text())
    assert len(rows) == CHECKPOINTS
    assert [r["rule"].split(" (")[0] for r in rows] == [f"step {s}" for s in (10, 20, 30, 40)]
    for row in rows:
        assert len(row["layers"]) == 8 and 0.0 <= row["f1"] <= 1.0
    assert "parameters, keep where p(E_e) < " in capsys.readouterr().out

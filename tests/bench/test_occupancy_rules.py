"""The occupancy-rules diagnostic scores O's decisions as the evaluation samples them: a threshold
rule read off the max-probability grid equals the predictor sampled into the grid, and a dilation
grows a cell into its 3^3 neighbourhood, clipped at the box."""

import pytest
import torch

from bench.occupancy_rules import (
    FIELD_STEPS,
    dilated,
    field_rules,
    main,
    occupancy_probability_grid,
)
from model.evaluation.occupancy import predicted_grid
from model.fields.hmoe import OccupancyNetwork


@pytest.mark.parametrize("threshold", [0.5, 0.9, 0.99])
def test_a_threshold_on_the_probability_grid_is_the_predictor_sampled_into_the_grid(threshold):
    torch.manual_seed(0)
    network = OccupancyNetwork(num_scene_experts=2, width=16, xyz_frequencies=2).eval()
    with torch.no_grad():  # logits spread wide and E_e favoured: O keeps a part of the box
        network.output.weight.mul_(20.0)
        network.output.bias[network.empty_index] += 25.0
    aabb = torch.tensor([[-2.0, -1.0, 0.0], [2.0, 1.0, 3.0]])
    keep_p, top1 = occupancy_probability_grid(network, aabb, resolution=8)
    expected = predicted_grid(lambda x: network.occupied(x, threshold), aabb, 8)
    assert torch.equal(keep_p > 1.0 - threshold, expected)
    assert torch.equal(top1, predicted_grid(lambda x: network.occupied(x, None), aabb, 8))
    # a random O keeps some cells and drops others at these thresholds: the test compares something
    assert 0 < int(expected.sum()) < 8**3


class Ball(torch.nn.Module):
    """A field whose density is `sigma` inside a ball and 0 outside."""

    def __init__(self, centre, radius: float, sigma: float):
        super().__init__()
        self.centre, self.radius, self.sigma = torch.tensor(centre), radius, sigma

    def forward(self, x, dirs, image):
        inside = (x - self.centre).norm(dim=-1) < self.radius
        return type("Out", (), {"sigma": inside.float() * self.sigma})()


def test_a_field_rule_keeps_the_cells_where_the_fields_alpha_over_its_step_reaches_the_bound():
    aabb = torch.tensor([[-2.0, -1.0, 0.0], [2.0, 1.0, 3.0]])
    step = float((aabb[1] - aabb[0]).norm()) / FIELD_STEPS
    inside = lambda x: (x - torch.tensor([0.5, 0.0, 1.5])).norm(dim=-1) < 0.8  # noqa: E731
    expected = predicted_grid(inside, aabb, 8)
    # alpha over one step: 1 - exp(-sigma * step); 0.02 reaches 0.01, 0.005 does not
    for alpha, kept in ((0.02, expected), (0.005, torch.zeros_like(expected))):
        sigma = -torch.log1p(torch.tensor(-alpha)).item() / step
        rules = field_rules(Ball([0.5, 0.0, 1.5], 0.8, sigma), aabb, 8, [0.01])
        assert list(rules) == [f"field alpha >= 0.01 (step diagonal/{FIELD_STEPS})"]
        assert torch.equal(next(iter(rules.values())), kept)
    assert 0 < int(expected.sum()) < 8**3


def test_a_dilation_grows_a_cell_into_its_neighbourhood_clipped_at_the_box():
    grid = torch.zeros(7, 7, 7, dtype=torch.bool)
    grid[3, 3, 3] = True
    grid[0, 0, 0] = True  # a corner: its neighbourhood inside the box is 2^3
    grown = dilated(grid, 1)
    assert int(grown.sum()) == 27 + 8
    assert grown[2:5, 2:5, 2:5].all() and grown[:2, :2, :2].all() and not grown[6, 6, 6]
    assert torch.equal(dilated(grid, 0), grid)


def test_bad_thresholds_are_named(capsys):
    with pytest.raises(SystemExit):
        main(["--run", "nowhere", "--thresholds", "0.9,1.5"])
    assert "each must lie in (0, 1)" in capsys.readouterr().err


def test_bad_field_alphas_are_named(capsys):
    with pytest.raises(SystemExit):
        main(["--run", "nowhere", "--field-alphas", "1"])
    assert "--field-alphas '1': each must lie in (0, 1)" in capsys.readouterr().err


def test_a_folder_without_a_finished_run_is_named(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit:
        main(["--run", str(tmp_path)])
    assert exit.value.code == 2
    assert str(tmp_path) in capsys.readouterr().err

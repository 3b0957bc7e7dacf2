"""Named profiles and `leco model info`."""

import json

import pytest
from pydantic import ValidationError

from cli.main import main
from model.model_info import model_info
from model.profiles import PROFILES, NetworkConfig, get_profile


def test_paper_profile_has_the_papers_numbers():
    p = get_profile("paper")
    assert (p.network.width, p.network.num_experts, p.network.expert_layers) == (256, 8, 7)
    assert (p.occupancy.samples_per_ray, p.occupancy.steps, p.occupancy.v) == (512, 40_000, 80.0)
    assert (p.occupancy.w_r, p.occupancy.w_g, p.occupancy.w_d) == (1.0, 5e-4, 0.1)
    assert (p.guided.coarse_samples, p.guided.split) == (128, 8)
    g, o = p.guided, p.occupancy  # the paper's formulation: none of the settings beyond the paper
    assert not (g.jitter or g.dilate or g.fallback or g.warm_start) and g.empty_threshold is None
    assert o.empty_gate_grad and o.w_v == 0 and o.lr_final is None and o.w_g_final is None
    assert (p.vanilla.coarse_samples, p.vanilla.fine_samples, p.rays_per_device) == (256, 512, 1024)
    assert p.grid.resolution == 128 and p.grid.decay == 0.95 and p.grid.warmup_steps == 256


def test_cpu_profile_keeps_the_papers_sampling_ratios():
    p = get_profile("cpu")
    vanilla = p.vanilla.coarse_samples + p.vanilla.fine_samples
    assert p.vanilla.fine_samples == 2 * p.vanilla.coarse_samples  # coarse:fine = 1:2
    assert vanilla == 6 * p.guided.coarse_samples  # 768 : 128 in the paper
    # Under placement the main samples are a fixed budget per hit ray (S+Prop's 21); split no longer
    # applies, and dilation keeps one bin either side of a kept one (docs/BENCHMARKS.md, measured).
    assert p.guided.placement and p.guided.main_samples == p.prop.main_samples == 21
    assert p.guided.dilate == 1 and p.guided.empty_threshold == 0.9
    assert p.grid.resolution == 128 and p.occupancy.v == 80.0 and p.occupancy.w_d == 0.1


def test_profiles_are_validated_and_frozen():
    with pytest.raises(ValidationError):
        NetworkConfig(width=0)
    with pytest.raises(ValidationError):
        NetworkConfig(widht=64)  # typo: extra fields are refused
    with pytest.raises(ValidationError):
        PROFILES["cpu"].network.width = 5
    with pytest.raises(ValueError, match="choose one of paper, cpu, smoke"):
        get_profile("fast")


def test_model_info_counts(capsys):
    leco = model_info("leco", get_profile("paper"))
    assert leco["components"]["occupancy_network"] == 153_865
    grid = model_info("grid", get_profile("paper"))
    assert grid["components"]["grid_cells"] == 128**3
    # LeCO's occupancy model is under a tenth of the grid's cells.
    assert leco["components"]["occupancy_network"] < 0.1 * grid["components"]["grid_cells"]
    assert main(["model", "info", "--method", "switch", "--profile", "smoke", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (
        info["total"] == sum(info["components"].values()) and "grid_cells" not in info["components"]
    )
    assert main(["model", "info", "--method", "nope"]) == 2

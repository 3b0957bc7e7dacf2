"""Metrics and the standalone occupancy predictor."""

import math

import pytest
import torch

from model.estimators.occupancy import OccupancyPredictor
from model.evaluation.metrics import occupancy_metrics, psnr, ssim
from model.fields import HMoE


def test_psnr_and_ssim_known_values():
    g = torch.Generator().manual_seed(0)
    image = torch.rand(32, 32, 3, generator=g)
    assert psnr(image, image) == math.inf and ssim(image, image) == pytest.approx(1.0, abs=1e-6)
    assert psnr(torch.zeros(4, 4, 3), torch.full((4, 4, 3), 0.1)) == pytest.approx(20.0)
    noisy = (image + 0.1 * torch.randn(32, 32, 3, generator=g)).clamp(0, 1)
    assert 0.3 < ssim(noisy, image) < 0.95
    assert ssim(torch.full((32, 32, 3), 0.5), image) < ssim(noisy, image)
    # images narrower than the 11-pixel window are scored with the largest odd window that fits
    for h, w in ((15, 5), (4, 30), (1, 1)):
        small = torch.rand(h, w, 3, generator=g)
        assert ssim(small, small) == pytest.approx(1.0, abs=1e-6)
        assert ssim((small + 0.3).clamp(0, 1), small) < 1.0 - 1e-3


def test_occupancy_metrics_counts():
    ref = torch.tensor([1, 1, 0, 0, 0, 0, 0, 0], dtype=torch.bool)
    pred = torch.tensor([1, 0, 1, 0, 0, 0, 0, 0], dtype=torch.bool)
    m = occupancy_metrics(pred, ref)
    assert (m["accuracy"], m["precision"], m["recall"], m["f1"]) == (0.75, 0.5, 0.5, 0.5)
    masked = occupancy_metrics(
        pred, ref, mask=torch.tensor([1, 1, 0, 1, 1, 1, 1, 1], dtype=torch.bool)
    )
    assert masked["precision"] == 1.0 and masked["recall"] == 0.5
    assert (
        occupancy_metrics(torch.zeros(4, dtype=torch.bool), torch.zeros(4, dtype=torch.bool))["f1"]
        == 0.0
    )


def test_predictor_saved_without_experts_gives_the_same_answers(tmp_path):
    torch.manual_seed(0)
    model = HMoE(num_images=4, width=32, num_scene_experts=4, expert_layers=2)
    predictor = OccupancyPredictor.from_hmoe(model)
    points = torch.rand(5000, 3) * 2 - 1
    expected = model.gate.occupied(points)
    assert torch.equal(predictor.occupied(points), expected)
    predictor.save(tmp_path / "occupancy.pt")
    loaded = OccupancyPredictor.load(tmp_path / "occupancy.pt")
    assert torch.equal(loaded.occupied(points), expected)
    size = (tmp_path / "occupancy.pt").stat().st_size
    model_params = sum(p.numel() for p in model.parameters())
    assert loaded.num_parameters < model_params / 3 and size < 4 * model_params  # only O travels
    torch.save({"weights": 1}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not a LeCO occupancy model"):
        OccupancyPredictor.load(tmp_path / "other.pt")

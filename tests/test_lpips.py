"""LPIPS loads only local weights: absent -> None with the reason; present (here: seeded stand-in weights in
the real file formats) -> a working distance."""

import torch

from model import lpips
from model.lpips import ALEXNET_FILE, CHANNELS, LINEAR_FILE, LPIPS, load_lpips


def isolate(monkeypatch, folder):
    monkeypatch.setenv("LECO_LPIPS_DIR", str(folder))
    monkeypatch.setenv("TORCH_HOME", str(folder / "torch-home"))
    monkeypatch.setattr(lpips.importlib.util, "find_spec", lambda name: None)


def write_weights(folder):
    torch.manual_seed(0)
    net = LPIPS()
    alexnet = {f"features.{k}": v for k, v in net.features.state_dict().items()}
    alexnet["classifier.1.weight"] = torch.zeros(1)  # torchvision's file also holds the classifier
    linear = {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1) for k, c in enumerate(CHANNELS)}
    torch.save(alexnet, folder / ALEXNET_FILE)
    torch.save(linear, folder / LINEAR_FILE)


def test_missing_weights_give_none_and_say_why(monkeypatch, tmp_path):
    isolate(monkeypatch, tmp_path)
    model, reason = load_lpips()
    assert model is None
    assert ALEXNET_FILE in reason and LINEAR_FILE in reason and "LECO_LPIPS_DIR" in reason and "null" in reason


def test_broken_weights_give_none_and_say_why(monkeypatch, tmp_path):
    isolate(monkeypatch, tmp_path)
    (tmp_path / ALEXNET_FILE).write_bytes(b"not a checkpoint")
    (tmp_path / LINEAR_FILE).write_bytes(b"not a checkpoint")
    model, reason = load_lpips()
    assert model is None and "could not be loaded" in reason


def test_local_weights_give_a_distance(monkeypatch, tmp_path):
    isolate(monkeypatch, tmp_path)
    write_weights(tmp_path)
    model, reason = load_lpips()
    assert model is not None and reason == ""
    g = torch.Generator().manual_seed(1)
    image = torch.rand(64, 64, 3, generator=g)
    near = (image + 0.02 * torch.randn(64, 64, 3, generator=g)).clamp(0, 1)
    far = (image + 0.3 * torch.randn(64, 64, 3, generator=g)).clamp(0, 1)
    assert model(image, image) == 0.0
    assert 0 < model(image, near) < model(image, far)
    assert abs(model(image, far) - model(far, image)) < 1e-6

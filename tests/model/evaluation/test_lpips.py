"""LPIPS with both backbones from local, hash-checked weights: our feature stacks take torchvision's
checkpoint layout; absent, mis-hashed or broken files give None with a reason that names them;
present files (seeded stand-in weights in the real file formats, with their hashes pinned by the
test) give a working distance; an evaluation reports `lpips_vgg` and `lpips_alex` with per-backbone
notes.

torchvision is not a dependency, so the torchvision-shaped state_dicts are built from torchvision's
published layer indices (its `features.<i>` convolutions) plus a classifier entry, which
torchvision's files also hold."""

import hashlib
import json

import pytest
import torch

from model.evaluation import lpips
from model.evaluation.lpips import BACKBONES, LPIPS, PINNED_SHA256, LPIPSScores, load_lpips

# Where torchvision's alexnet() and vgg16() keep their convolutions inside `features` (and their
# widths).
TORCHVISION_CONVS = {
    "alex": {0: 64, 3: 192, 6: 384, 8: 256, 10: 256},
    "vgg": {
        0: 64,
        2: 64,
        5: 128,
        7: 128,
        10: 256,
        12: 256,
        14: 256,
        17: 512,
        19: 512,
        21: 512,
        24: 512,
        26: 512,
        28: 512,
    },
}


def isolate(monkeypatch, folder):
    """Only `folder` is searched: no hub cache, no installed lpips package."""
    monkeypatch.setenv("LECO_LPIPS_DIR", str(folder))
    monkeypatch.setenv("TORCH_HOME", str(folder / "torch-home"))
    monkeypatch.setattr(lpips.importlib.util, "find_spec", lambda name: None)


def torchvision_state_dict(backbone: str, seed: int) -> dict:
    """A checkpoint in torchvision's layout (features.<i>.weight/bias, classifier.*) with seeded
    weights."""
    g = torch.Generator().manual_seed(seed)
    state, channels = {}, 3
    for index, width in TORCHVISION_CONVS[backbone].items():
        size = (11 if index == 0 else 5 if index == 3 else 3) if backbone == "alex" else 3
        state[f"features.{index}.weight"] = (
            torch.randn(width, channels, size, size, generator=g) * 0.05
        )
        state[f"features.{index}.bias"] = torch.randn(width, generator=g) * 0.01
        channels = width
    # torchvision's files also hold the classifier: ignored
    state["classifier.1.weight"] = torch.zeros(4, 2)
    return state


def lpips_linear(backbone: str, seed: int) -> dict:
    """lpips' v0.1 format: lin<k>.model.1.weight, non-negative (1, C, 1, 1)."""
    g = torch.Generator().manual_seed(seed)
    return {
        f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1, generator=g)
        for k, c in enumerate(BACKBONES[backbone].channels)
    }


def stage(folder, backbone: str) -> dict[str, str]:
    """Write the backbone's two files into `folder`; return pins holding their sha256 (the test's
    'published')."""
    spec = BACKBONES[backbone]
    torch.save(torchvision_state_dict(backbone, seed=0), folder / spec.trunk_file)
    torch.save(lpips_linear(backbone, seed=1), folder / spec.linear_file)
    return {
        name: hashlib.sha256((folder / name).read_bytes()).hexdigest()
        for name in (spec.trunk_file, spec.linear_file)
    }


def images():
    g = torch.Generator().manual_seed(2)
    image = torch.rand(48, 64, 3, generator=g)
    near = (image + 0.02 * torch.randn(48, 64, 3, generator=g)).clamp(0, 1)
    far = (image + 0.3 * torch.randn(48, 64, 3, generator=g)).clamp(0, 1)
    return image, near, far


@pytest.mark.parametrize("backbone", ["alex", "vgg"])
def test_feature_stacks_take_torchvision_layout(backbone):
    model = LPIPS(backbone)
    convs = {
        i: layer.out_channels
        for i, layer in enumerate(model.features)
        if isinstance(layer, torch.nn.Conv2d)
    }
    assert convs == TORCHVISION_CONVS[backbone]
    # each tap is the ReLU right after a convolution of that width
    assert [
        model.features[i].out_channels for i in (t - 1 for t in BACKBONES[backbone].taps)
    ] == list(BACKBONES[backbone].channels)
    # strict
    model.load_weights(torchvision_state_dict(backbone, seed=0), lpips_linear(backbone, seed=1))


def test_vgg_taps_are_relu1_2_to_relu5_3():
    model = LPIPS("vgg")
    assert BACKBONES["vgg"].taps == (3, 8, 15, 22, 29) and len(model.features) == 30
    assert all(isinstance(model.features[t], torch.nn.ReLU) for t in BACKBONES["vgg"].taps)
    pools = [i for i, layer in enumerate(model.features) if isinstance(layer, torch.nn.MaxPool2d)]
    assert pools == [4, 9, 16, 23]  # relu<k>_* sit between these, as in torchvision's vgg16


@pytest.mark.parametrize("backbone", ["alex", "vgg"])
def test_local_weights_with_matching_hashes_give_a_distance(monkeypatch, tmp_path, backbone):
    isolate(monkeypatch, tmp_path)
    pins = stage(tmp_path, backbone)
    model, reason = load_lpips(backbone, pins=pins)
    assert model is not None and reason == "" and model.backbone == backbone
    image, near, far = images()
    assert model(image, image) == 0.0
    assert 0 < model(image, near) < model(image, far)
    assert abs(model(image, far) - model(far, image)) < 1e-6


def test_the_default_is_alexnet_for_existing_callers(monkeypatch, tmp_path):
    isolate(monkeypatch, tmp_path)
    pins = stage(tmp_path, "alex")
    monkeypatch.setattr(lpips, "PINNED_SHA256", pins)
    model, reason = load_lpips()
    assert model is not None and model.backbone == "alex", reason


def test_a_file_with_another_hash_is_refused_naming_it(monkeypatch, tmp_path):
    isolate(monkeypatch, tmp_path)
    pins = stage(tmp_path, "vgg")
    actual = pins["vgg.pth"]
    pins["vgg.pth"] = "0" * 64
    model, reason = load_lpips("vgg", pins=pins)
    assert model is None
    assert (
        "vgg.pth" in reason
        and str(tmp_path / "vgg.pth") in reason
        and actual in reason
        and "0" * 64 in reason
    )
    assert "vgg16-397923af.pth" not in reason  # the trunk matched its pin


def test_the_published_hashes_are_pinned_by_default(monkeypatch, tmp_path):
    isolate(monkeypatch, tmp_path)
    stage(tmp_path, "vgg")  # stand-ins under the real names: not the published files
    model, reason = load_lpips("vgg")
    assert model is None
    assert PINNED_SHA256["vgg16-397923af.pth"] in reason and PINNED_SHA256["vgg.pth"] in reason
    assert all(
        len(h) == 64 and h.startswith(name.rsplit("-", 1)[-1].removesuffix(".pth"))
        # torchvision names carry the prefix
        for name, h in PINNED_SHA256.items()
        if "-" in name
    )


def test_missing_weights_give_none_and_say_why(monkeypatch, tmp_path):
    isolate(monkeypatch, tmp_path / "no-such-folder")
    for backbone in ("vgg", "alex"):
        model, reason = load_lpips(backbone)
        spec = BACKBONES[backbone]
        assert model is None
        assert (
            spec.trunk_file in reason and spec.linear_file in reason and f"({backbone})" in reason
        )
        assert (
            "LECO_LPIPS_DIR" in reason
            and "null" in reason
            and str(tmp_path / "no-such-folder") in reason
        )


def test_broken_weights_with_matching_hashes_give_none_and_say_why(monkeypatch, tmp_path):
    isolate(monkeypatch, tmp_path)
    (tmp_path / "alexnet-owt-7be5be79.pth").write_bytes(b"not a checkpoint")
    (tmp_path / "alex.pth").write_bytes(b"not a checkpoint")
    pins = {
        name: hashlib.sha256(b"not a checkpoint").hexdigest()
        for name in ("alexnet-owt-7be5be79.pth", "alex.pth")
    }
    model, reason = load_lpips("alex", pins=pins)
    assert model is None and "could not be loaded" in reason


def test_a_vgg_checkpoint_under_the_alexnet_name_is_not_loaded(monkeypatch, tmp_path):
    isolate(monkeypatch, tmp_path)
    torch.save(torchvision_state_dict("vgg", seed=0), tmp_path / "alexnet-owt-7be5be79.pth")
    torch.save(lpips_linear("alex", seed=1), tmp_path / "alex.pth")
    pins = {
        name: hashlib.sha256((tmp_path / name).read_bytes()).hexdigest()
        for name in ("alexnet-owt-7be5be79.pth", "alex.pth")
    }
    model, reason = load_lpips("alex", pins=pins)
    assert model is None and "could not be loaded" in reason


def test_an_unknown_backbone_is_a_reason_not_a_crash():
    model, reason = load_lpips("squeeze")
    assert model is None and "squeeze" in reason


def test_evaluation_scores_label_both_backbones(monkeypatch, tmp_path):
    isolate(monkeypatch, tmp_path)
    pins = stage(tmp_path, "vgg")  # AlexNet's files are absent
    scores = LPIPSScores(pins=pins)
    image, near, _ = images()
    scores.add(image, image)
    scores.add(image, near)
    report = scores.report()
    assert set(report) == {"lpips_vgg", "lpips_alex", "lpips_note"}
    assert 0 < report["lpips_vgg"] < 1 and report["lpips_alex"] is None
    assert report["lpips_note"]["vgg"] is None
    assert (
        "alexnet-owt-7be5be79.pth" in report["lpips_note"]["alex"]
        and "null" in report["lpips_note"]["alex"]
    )


def test_evaluation_without_any_weights_reports_both_as_null(monkeypatch, tmp_path):
    isolate(monkeypatch, tmp_path)
    scores = LPIPSScores()
    scores.add(*images()[:2])
    report = scores.report()
    assert report["lpips_vgg"] is None and report["lpips_alex"] is None
    assert (
        "vgg16-397923af.pth" in report["lpips_note"]["vgg"]
        and "alex.pth" in report["lpips_note"]["alex"]
    )


def test_a_finished_run_reports_lpips_per_backbone(monkeypatch, tmp_path, tiny_scene):
    """End to end: a short run's eval.json and summary.json carry lpips_vgg (scored from the staged
    stand-ins), lpips_alex (null: its files are absent) and the per-backbone notes; no unlabelled
    `lpips` is left."""
    from workers.config import TrainConfig
    from workers.train.run import run_training

    weights = tmp_path / "weights"
    weights.mkdir()
    isolate(monkeypatch, weights)
    monkeypatch.setattr(lpips, "PINNED_SHA256", {**PINNED_SHA256, **stage(weights, "vgg")})
    cfg = TrainConfig(
        method="switch", profile="smoke", overrides={"main_steps": 4}, val_appearance_steps=2
    )
    summary = run_training(cfg, tiny_scene.root, tmp_path / "run", backend="local")
    for val in (summary["val"], json.loads((tmp_path / "run" / "eval.json").read_text())["val"]):
        assert "lpips" not in val
        assert (
            isinstance(val["lpips_vgg"], float)
            and val["lpips_vgg"] > 0
            and val["lpips_alex"] is None
        )
        assert (
            val["lpips_note"]["vgg"] is None
            and "alexnet-owt-7be5be79.pth" in val["lpips_note"]["alex"]
        )


def test_an_image_too_small_for_a_backbone_makes_it_null_not_a_crash(monkeypatch, tmp_path):
    isolate(monkeypatch, tmp_path)
    pins = {**stage(tmp_path, "vgg"), **stage(tmp_path, "alex")}
    scores = LPIPSScores(pins=pins)
    # VGG keeps 1 pixel of 20; AlexNet's stride-4 stem and 3x3 pools keep none
    tiny = torch.rand(20, 20, 3)
    scores.add(tiny, tiny)
    report = scores.report()
    assert report["lpips_alex"] is None and "could not be scored" in report["lpips_note"]["alex"]
    assert report["lpips_vgg"] == 0.0 and report["lpips_note"]["vgg"] is None

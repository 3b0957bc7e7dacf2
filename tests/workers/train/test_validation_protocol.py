"""The validation protocol: no validation view is coloured by an embedding the run never trained.
Right halves are scored; every embedding the phase renders with starts from the mean of the training
views' embeddings and is fitted on left-half pixels, with the networks frozen."""

import json

import pytest
import torch

from model.scenes.rays import PixelTable
from workers.appearance import (
    phase_embeddings,
    prepare_validation_appearance,
    protocol,
    right_columns,
)
from workers.config import TrainConfig
from workers.models import build_models
from workers.train.evaluate import evaluate_run
from workers.train.run import run_training


def models_for(scene, method="switch"):
    cfg = TrainConfig(method=method, profile="smoke")
    run_method = cfg.method_for_run()
    return run_method, build_models(run_method, scene.num_images, scene.bounds.aabb, seed=0)


def poison_validation_rows(run_method, models, phase, views):
    with torch.no_grad():
        for e in phase_embeddings(run_method, models, phase):
            e.weight[views.appearance] = 1e3


@pytest.mark.parametrize(
    "method,phase", [("switch", "main"), ("leco", "occupancy"), ("grid", "main")]
)
def test_mean_policy_replaces_untrained_validation_embeddings(tiny_scene, method, phase):
    run_method, models = models_for(tiny_scene, method)
    val, train = tiny_scene.splits["val"], tiny_scene.train
    poison_validation_rows(run_method, models, phase, val)
    before = {id(e): e.weight.detach().clone() for e in phase_embeddings(run_method, models, phase)}
    assert len(before) == 2  # the field's and the background's
    prepare_validation_appearance(
        run_method,
        models,
        phase,
        val,
        train,
        list(range(len(val))),
        tiny_scene.bounds.aabb,
        torch.device("cpu"),
        steps=0,
    )
    for e in phase_embeddings(run_method, models, phase):
        w = e.weight.detach()
        assert torch.allclose(
            w[val.appearance], before[id(e)][train.appearance].mean(0).expand(len(val), -1)
        )
        # training rows untouched
        assert torch.equal(w[train.appearance], before[id(e)][train.appearance])


def test_fitting_on_left_halves_lowers_their_error_and_moves_only_validation_rows(tiny_scene):
    run_method, models = models_for(tiny_scene)
    val, train = tiny_scene.splits["val"], tiny_scene.train
    before = [e.weight.detach().clone() for e in phase_embeddings(run_method, models, "main")]
    result = prepare_validation_appearance(
        run_method,
        models,
        "main",
        val,
        train,
        [0],
        tiny_scene.bounds.aabb,
        torch.device("cpu"),
        steps=20,
    )
    assert result.loss_after < 0.95 * result.loss_before
    for old, e in zip(before, phase_embeddings(run_method, models, "main")):
        moved = (e.weight.detach() != old).any(dim=1)
        assert moved.nonzero().squeeze(1).tolist() == [int(val.appearance[0])]
    # the networks are trainable again afterwards
    assert all(p.requires_grad for p in models.parameters())


def test_scored_columns_are_the_right_half(tiny_scene):
    val = tiny_scene.splits["val"]
    table = PixelTable(val)
    w, h = int(val.cameras.width[0]), val.images[0].shape[0]
    u0, u1 = right_columns(val, 0)
    assert (u0, u1) == (w // 2, w)
    _, u, _ = table.locate(table.image_pixels(0, (u0, u1)))
    assert int(u.min()) == w // 2 and len(u) == h * (w - w // 2)


def test_final_evaluation_ignores_whatever_the_validation_embeddings_held(tiny_scene, tmp_path):
    cfg = TrainConfig(
        method="switch", profile="smoke", overrides={"main_steps": 10}, val_appearance_steps=4
    )
    summary = run_training(cfg, tiny_scene.root, tmp_path / "run", backend="local")
    assert summary["val"]["protocol"] == protocol(4) and "left halves" in summary["val"]["protocol"]
    final = tmp_path / "run" / "final" / "models.pt"
    saved = torch.load(final, weights_only=False)
    rows = tiny_scene.splits["val"].appearance
    for key in ("field.appearance.weight", "background.appearance.weight"):
        saved["models"][key][rows] = torch.randn(len(rows), saved["models"][key].shape[1]) * 50
    torch.save(saved, final)
    again = evaluate_run(tmp_path / "run")
    assert again["val"]["psnr"] == pytest.approx(summary["val"]["psnr"], abs=1e-4)
    assert json.loads((tmp_path / "run" / "eval.json").read_text())["val"]["views"] == len(rows)

"""A run keeps the profile it trained with: a later change of a profile's defaults reaches neither a
finished run that is loaded to render nor a run that resumes."""

import json

import pytest
import torch

from model.profiles import PROFILES
from workers.config import TrainConfig
from workers.train.run import RunError, prepare_run_dir, run_training
from workers.trained import load_run


def wider_smoke(monkeypatch) -> None:
    """Today's `smoke` profile with twice the experts' width: a default change that alters the
    networks' shapes, so a run re-resolved from its job config could not even load."""
    smoke = PROFILES["smoke"]
    network = smoke.network.model_copy(update={"width": 2 * smoke.network.width})
    monkeypatch.setitem(PROFILES, "smoke", smoke.model_copy(update={"network": network}))


@pytest.fixture
def finished(tiny_scene, tmp_path):
    cfg = TrainConfig(method="switch", profile="smoke", overrides={"main_steps": 3})
    summary = run_training(cfg, tiny_scene.root, tmp_path / "run", backend="local")
    return cfg, summary, tmp_path / "run"


def test_a_finished_run_loads_with_the_profile_it_trained_with(finished, monkeypatch):
    cfg, summary, run = finished
    width = cfg.resolved_profile().network.width
    wider_smoke(monkeypatch)
    assert TrainConfig(**cfg.model_dump()).resolved_profile().network.width == 2 * width
    trained = load_run(run)
    assert trained.cfg.resolved_profile().network.width == width
    assert trained.cfg.model_dump() == cfg.model_dump()  # the job config itself is unchanged
    assert trained.cfg.resolved_profile().model_dump(mode="json") == summary["resolved_profile"]


def test_a_run_saved_before_models_pt_held_its_profile_takes_it_from_its_summary(
    finished, monkeypatch
):
    cfg, _, run = finished
    saved = torch.load(run / "final" / "models.pt", weights_only=False)
    del saved["resolved_profile"]
    torch.save(saved, run / "final" / "models.pt")
    wider_smoke(monkeypatch)
    assert load_run(run).cfg.resolved_profile().network.width == 16
    (run / "summary.json").unlink()  # nothing left to say what it trained with
    with pytest.raises(RuntimeError, match="size mismatch"):
        load_run(run)


def test_a_run_resumes_with_the_profile_it_started_with(tiny_scene, tmp_path, monkeypatch):
    cfg = TrainConfig(method="switch", profile="smoke", overrides={"main_steps": 3})
    started = prepare_run_dir(cfg, tiny_scene.root, tmp_path / "run")
    wider_smoke(monkeypatch)
    resumed = prepare_run_dir(cfg, tiny_scene.root, tmp_path / "run")
    assert resumed.resolved_profile() == started.resolved_profile()
    assert resumed.resolved_profile().network.width == 16
    record = json.loads((tmp_path / "run" / "run.json").read_text())
    assert record["resolved_profile"]["network"]["width"] == 16
    # a new run of the same job takes today's defaults
    assert prepare_run_dir(cfg, tiny_scene.root, tmp_path / "new").resolved_profile() != (
        started.resolved_profile()
    )


def test_a_service_attempt_resumes_a_checkpoint_with_its_profile(
    finished, tiny_scene, tmp_path, monkeypatch
):
    """A later attempt starts in a fresh folder from the job's stored checkpoint: the checkpoint
    carries the profile, and the run finishes with it."""
    cfg, summary, run = finished
    wider_smoke(monkeypatch)
    again = run_training(
        cfg,
        tiny_scene.root,
        tmp_path / "attempt2",
        backend="local",
        resume_from=run / "checkpoints" / "latest",
    )
    assert again["resolved_profile"] == summary["resolved_profile"]
    assert again["steps"]["total"] == summary["steps"]["total"]


def test_a_checkpoint_whose_settings_this_version_cannot_read_is_refused(tiny_scene, tmp_path):
    cfg = TrainConfig(method="switch", profile="smoke")
    seed = tmp_path / "seed"
    seed.mkdir()
    profile = cfg.resolved_profile().model_dump(mode="json")
    profile["network"]["retired_setting"] = 1
    torch.save({"resolved_profile": profile}, seed / "state.pt")
    with pytest.raises(RunError, match="cannot resume: the run was trained with settings"):
        prepare_run_dir(cfg, tiny_scene.root, tmp_path / "run", resume_from=seed)


def test_a_profile_saved_before_ngp_leco_had_its_own_section_still_loads():
    # what an ngp-leco run saved when its sampler lived under `ngp.*`: its resolved guided and
    # occupancy already held ngp-leco's values
    new = TrainConfig(method="ngp-leco", profile="cpu").resolved_profile()
    old = new.model_dump(mode="json")
    del old["ngp_leco"]
    old["ngp"].update(main_samples=42, coarse_samples=64, split=2, dilate=1, placement=False)
    old["ngp"].update(placement_in_phase1=False, online_warmup=250, occupancy_budget_share=0.08)
    pinned = TrainConfig(method="ngp-leco", profile="cpu").pinned(old).resolved_profile()
    assert pinned == new
    assert (pinned.guided.coarse_samples, pinned.occupancy.budget_share) == (64, 0.08)
    # any other method's old profile loads as it was saved
    leco = TrainConfig(method="leco", profile="cpu")
    saved = leco.resolved_profile().model_dump(mode="json")
    del saved["ngp_leco"]
    saved["ngp"].update(main_samples=42, coarse_samples=64)
    assert leco.pinned(saved).resolved_profile().guided == leco.resolved_profile().guided

"""A LeCO run on the synthetic city as `make run` trains it (cpu profile, 1,500 + 1,500 steps, one
local process): trained once a session, about three minutes on two cores, and read by the
tests that need a trained model of a real size (the pipeline's occupancy, the point-cloud
export)."""

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def city_leco_run(city_scene, tmp_path_factory) -> Path:
    from workers.config import TrainConfig
    from workers.train.run import run_training

    run_dir = tmp_path_factory.mktemp("city-leco") / "run"
    # the validation protocol's appearance fit is not what these tests read
    cfg = TrainConfig(method="leco", profile="cpu", checkpoint_every=1000, val_appearance_steps=0)
    run_training(cfg, city_scene[0], run_dir, backend="local")
    return run_dir

"""Training on a local Ray (2 CPU workers, gloo): data parallel equals one worker on the whole
batch, and a killed worker is restarted from the last checkpoint by Ray Train with a clean metric
series."""

import os
import signal
import threading
import time
from pathlib import Path

import pytest
import torch

from workers.config import TrainConfig
from workers.train.run import HEALTH_CHECK_ENV, HEALTH_CHECK_S, run_training
from workers.train.sinks import read_metrics

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("local_ray")]

DETERMINISTIC = {
    "perturb": False,
    "network.density_noise": 0.0,
    "balance_weight": 0.0,
    "main_steps": 1,
}


def final_parameters(run_dir):
    return torch.load(run_dir / "final" / "models.pt", weights_only=False)["models"]


def test_two_workers_on_halves_equal_one_worker_on_the_whole_batch(
    tiny_scene, tmp_path, monkeypatch
):
    """Per-ray losses average exactly over equal shares. (Batch-statistic losses, the balance loss
    and Eq. 1/2, are computed per rank on its share, as in Switch-NeRF's data parallel: off here.)
    The two-worker run is given relative paths, as a user types them: Ray's workers run in folders
    of their own."""
    one = TrainConfig(
        method="switch", profile="smoke", overrides={**DETERMINISTIC, "rays_per_device": 128}
    )
    two = TrainConfig(
        method="switch",
        profile="smoke",
        workers=2,
        overrides={**DETERMINISTIC, "rays_per_device": 64},
    )
    assert one.global_batch == two.global_batch == 128
    run_training(one, tiny_scene.root, tmp_path / "one")
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv(HEALTH_CHECK_ENV, raising=False)
    run_training(two, Path(os.path.relpath(tiny_scene.root, tmp_path)), Path("two"))
    # handed to Ray Train's controller with the job: it sees the workers finish within 0.5 s
    assert os.environ[HEALTH_CHECK_ENV] == HEALTH_CHECK_S
    initial = TrainConfig(method="switch", profile="smoke", overrides={**DETERMINISTIC})
    from workers.models import build_models

    start = build_models(
        initial.method_for_run(), tiny_scene.num_images, tiny_scene.bounds.aabb, 0
    ).state_dict()
    a, b = final_parameters(tmp_path / "one"), final_parameters(tmp_path / "two")
    moved = 0
    for name in a:
        assert torch.allclose(a[name], b[name], atol=1e-6, rtol=0), name
        moved += int(not torch.equal(a[name], start[name]))
    assert moved > 10  # the step really changed the networks


def test_killed_worker_restarts_from_the_last_checkpoint(tiny_scene, tmp_path):
    cfg = TrainConfig(
        method="switch",
        profile="smoke",
        workers=2,
        checkpoint_every=50,
        metrics_every=10,
        overrides={"main_steps": 300},
    )
    out = tmp_path / "run"
    killed = {}

    def kill_rank1():
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline:
            rows = read_metrics(out / "metrics.jsonl")
            if rows and rows[-1]["step"] >= 70 and (out / "workers" / "rank1.pid").exists():
                pid = int((out / "workers" / "rank1.pid").read_text())
                killed.update(pid=pid, step=rows[-1]["step"])
                os.kill(pid, signal.SIGKILL)
                return
            time.sleep(0.05)

    killer = threading.Thread(target=kill_rank1)
    killer.start()
    summary = run_training(cfg, tiny_scene.root, out)
    killer.join()
    assert killed, "the worker was never killed"
    assert killed["step"] < 300
    assert int((out / "workers" / "rank1.pid").read_text()) != killed["pid"]  # a new worker process
    rows = read_metrics(out / "metrics.jsonl")
    assert [r["step"] for r in rows] == list(range(10, 301, 10))
    assert len((out / "metrics.jsonl").read_text().splitlines()) == len(rows)
    assert summary["steps"]["total"] == 300 and summary["world_size"] == 2

"""Ctrl-C on `leco serve` (the embedded default) in the middle of a job: the terminal sends SIGINT
to the whole process group, so the local Ray dies under the run at the same moment. The job must go
back to the queue with the reason, not be failed by the error Ray's death causes, and the next `leco
serve` must resume it from its last checkpoint and finish it with every metric step once."""

import os
import signal
import sqlite3
import time

import pytest

from bench.load import Service, start_job
from tests.helpers import wait_for

pytestmark = pytest.mark.slow


def stop(service: Service) -> None:
    if service.process.poll() is None:
        service.__exit__(None, None, None)
    else:
        service.log.close()


def test_ctrl_c_on_leco_serve_returns_the_job_to_the_queue_and_a_restart_finishes_it(tmp_path):
    data = tmp_path / "data"
    first = Service(data, None).__enter__()
    try:
        with first.client() as api:
            job_id = start_job(api, "smoke", {"main_steps": 400})  # checkpoints every 50 steps
            wait_for(api, job_id, lambda j: j["step"] >= 80)
        started = time.monotonic()
        os.killpg(first.process.pid, signal.SIGINT)  # Ctrl-C in the terminal
        first.process.wait(60)
        assert time.monotonic() - started < 30
    finally:
        stop(first)
    with sqlite3.connect(data / "leco.db") as db:
        state, attempts, error = db.execute(
            "SELECT state, attempts, error FROM jobs WHERE id = ?", (job_id,)
        ).fetchone()
    assert (state, attempts) == ("queued", 1) and "its dispatcher" in error, (
        state,
        attempts,
        error,
    )
    log = (data / "serve.log").read_text()
    assert (
        "returned to the queue" in log and "Traceback" not in log.split("returned to the queue")[-1]
    )

    second = Service(data, None).__enter__()  # same data folder and database: the next `leco serve`
    try:
        with second.client() as api:
            job = wait_for(
                api, job_id, lambda j: j["state"] in ("succeeded", "failed", "cancelled")
            )
            assert job["state"] == "succeeded" and job["attempts"] == 2, job
            series = api.get(
                f"/v1/jobs/{job_id}/metrics", params={"phase": "main", "name": "loss"}
            ).json()["series"]
            steps = [p["step"] for p in series[0]["points"]]
            assert steps == list(range(steps[0], 421, 5)) and steps[0] <= 25  # no gap, no duplicate
    finally:
        stop(second)

"""The cluster path: a dispatcher with a Ray Jobs API address submits the job as a Ray job with the
deterministic submission id `leco-job-<id>-attempt-<n>` to a real `ray start --head` on loopback,
follows it, and the job's own process (python -m service.execute) trains and stores everything in
the database."""

import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from service.dispatcher import Dispatcher, submission_id
from service.settings import Settings
from tests.helpers import ON_POSTGRESQL, api_client, free_port

pytestmark = pytest.mark.slow
BIN = Path(sys.executable).parent


@pytest.fixture
def ray_head(tmp_path):
    ray = BIN / "ray"
    if not ray.exists():
        pytest.skip(f"no `ray` command beside {sys.executable}")
    gcs, dashboard = free_port(), free_port()
    # The Ray job's entrypoint says `python`: put this interpreter first on the head's PATH.
    env = {
        **os.environ,
        "RAY_AUTH_MODE": "disabled",
        "PATH": f"{BIN}:{os.environ['PATH']}",
        "RAY_USAGE_STATS_ENABLED": "0",
    }
    env.pop("RAY_ADDRESS", None)
    temp = Path("/tmp") / f"ray-leco-{os.getpid()}"  # Ray's socket paths must stay short
    started = subprocess.run(
        [
            str(ray),
            "start",
            "--head",
            f"--port={gcs}",
            "--num-cpus=2",
            "--include-dashboard=true",
            "--dashboard-host=127.0.0.1",
            f"--dashboard-port={dashboard}",
            f"--temp-dir={temp}",
            "--disable-usage-stats",
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert started.returncode == 0, started.stdout + started.stderr
    try:
        yield f"http://127.0.0.1:{dashboard}"
    finally:
        subprocess.run([str(ray), "stop", "--force"], env=env, capture_output=True, timeout=120)
        shutil.rmtree(temp, ignore_errors=True)


@ON_POSTGRESQL
def test_a_job_submitted_through_the_ray_jobs_api_runs_on_the_cluster(service_settings, ray_head):
    settings = Settings(**{**service_settings.model_dump(), "ray_address": ray_head})
    with api_client(settings) as api:
        assert api.get("/readyz").json()["checks"] == {"database": "up", "ray": "up"}
        scene = api.post("/v1/scenes/synthetic", json={"preset": "tiny", "seed": 0}).json()
        while scene["state"] == "generating":
            time.sleep(0.2)
            scene = api.get(f"/v1/scenes/{scene['id']}").json()
        job = api.post(
            "/v1/jobs",
            json={
                "scene": scene["id"],
                "method": "grid",
                "profile": "smoke",
                "workers": 2,
                "metrics_every": 5,
            },
        ).json()
        dispatcher = Dispatcher(settings, poll_s=0.5)
        thread = threading.Thread(target=dispatcher.run_forever, daemon=True)
        thread.start()
        try:
            deadline = time.monotonic() + 400
            while time.monotonic() < deadline:
                job = api.get(f"/v1/jobs/{job['id']}").json()
                if job["state"] in ("succeeded", "failed", "cancelled"):
                    break
                time.sleep(1)
        finally:
            dispatcher.stop(wait=True)
        from ray.job_submission import JobSubmissionClient

        client = JobSubmissionClient(ray_head)
        sid = submission_id(job["id"], 1)
        logs = client.get_job_logs(sid)
        assert job["state"] == "succeeded", (job["error"], logs[-3000:])
        assert str(client.get_job_status(sid)) in ("SUCCEEDED", "JobStatus.SUCCEEDED")
        assert f"job {job['id']} attempt 1: succeeded" in logs
        series = api.get(f"/v1/jobs/{job['id']}/metrics", params={"name": "loss"}).json()["series"][
            0
        ]
        assert [p["step"] for p in series["points"]] == [5, 10, 15, 20]
        names = {a["name"] for a in api.get(f"/v1/jobs/{job['id']}/artifacts").json()}
        assert {"summary.json", "final/models.pt", "occupancy.ply"} <= names

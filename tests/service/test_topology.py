"""The docker-compose topology without Docker: PostgreSQL, a one-shot `leco db upgrade`, a Ray head
(`ray start --head --num-cpus=0`) and a CPU Ray worker node joined to it, the API (`leco serve
--no-dispatcher`) and a dispatcher (`leco dispatch`), each its own process on loopback, with Ray
token auth and an API token set as docker-compose.yml sets them. On it: a smoke job end to end
through `leco submit` (the dispatcher submits it to the Ray Jobs API as `leco-job-<id>-attempt-<n>`,
and Ray's own CLI reads its status and log back), a Ray worker killed with SIGKILL mid-phase, and
the API killed and restarted mid-job while clients poll; each checks nothing was lost."""

import hashlib
import json
import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest

from tests.helpers import ROOT, drop_postgres_database, free_port, fresh_postgres_database, steps_of
from tests.helpers import wait_for as wait_for_job

pytestmark = pytest.mark.slow
BIN = Path(sys.executable).parent
TERMINAL = ("succeeded", "failed", "cancelled")


class Topology:
    def __init__(self, tmp: Path):
        self.data, self.port, self.gcs, self.dashboard = (
            tmp / "data",
            free_port(),
            free_port(),
            free_port(),
        )
        self.token, self.ray_temp = (
            secrets.token_urlsafe(24),
            Path("/tmp") / f"ray-topo-{os.getpid()}",
        )
        self.database_url = fresh_postgres_database()
        self.env = {
            **os.environ,
            "DATABASE_URL": self.database_url,
            "LECO_DATA_DIR": str(self.data),
            "LECO_API_TOKENS": self.token,
            "LECO_RAY_JOBS_ADDRESS": f"http://127.0.0.1:{self.dashboard}",
            "LECO_LEASE_S": "30",
            "RAY_AUTH_MODE": "token",
            "RAY_AUTH_TOKEN": secrets.token_urlsafe(24),
            # The Ray job's entrypoint says `python`: this interpreter first on every node's PATH.
            "PATH": f"{BIN}:{os.environ['PATH']}",
            "RAY_USAGE_STATS_ENABLED": "0",
        }
        self.env.pop("RAY_ADDRESS", None)
        self.logs = tmp / "logs"
        self.logs.mkdir()
        self.processes: dict[str, subprocess.Popen] = {}

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def run(self, *args: str, timeout: float = 180) -> subprocess.CompletedProcess:
        done = subprocess.run(
            list(args), env=self.env, cwd=ROOT, capture_output=True, text=True, timeout=timeout
        )
        assert done.returncode == 0, (
            f"{' '.join(args)}:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}"
        )
        return done

    def start(self, name: str, *args: str) -> None:
        log = open(self.logs / f"{name}.log", "a")
        self.processes[name] = subprocess.Popen(
            [sys.executable, "-m", "cli", *args],
            env=self.env,
            cwd=ROOT,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )

    def kill(self, name: str) -> None:
        process = self.processes.pop(name)
        try:
            os.killpg(process.pid, signal.SIGKILL)  # the whole container, as `docker kill` would
        except ProcessLookupError:
            pass
        process.wait(30)

    def start_api(self) -> None:
        self.start(
            "api", "serve", "--host", "127.0.0.1", "--port", str(self.port), "--no-dispatcher"
        )
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                ready = httpx.get(f"{self.url}/readyz", timeout=5)
                if ready.status_code == 200:
                    return
            except httpx.TransportError:
                pass
            assert self.processes["api"].poll() is None, (self.logs / "api.log").read_text()[-3000:]
            time.sleep(0.5)
        raise AssertionError(
            f"the API never became ready: {ready.text if 'ready' in dir() else ''}"
        )

    def client(self) -> httpx.Client:
        return httpx.Client(
            base_url=self.url, headers={"Authorization": f"Bearer {self.token}"}, timeout=30
        )

    def up(self) -> None:
        ray = str(BIN / "ray")
        self.run(sys.executable, "-m", "cli", "db", "upgrade")  # the one-shot migrate service
        self.run(
            ray,
            "start",
            "--head",
            f"--port={self.gcs}",
            "--num-cpus=0",
            "--include-dashboard=true",
            "--dashboard-host=127.0.0.1",
            f"--dashboard-port={self.dashboard}",
            f"--temp-dir={self.ray_temp}",
            "--disable-usage-stats",
        )
        self.run(
            ray, "start", f"--address=127.0.0.1:{self.gcs}", "--num-cpus=2", "--disable-usage-stats"
        )
        self.start_api()
        self.start("dispatcher", "dispatch", "--slots", "1")

    def down(self) -> None:
        for name in list(self.processes):
            self.kill(name)
        subprocess.run(
            [str(BIN / "ray"), "stop", "--force"], env=self.env, capture_output=True, timeout=120
        )
        shutil.rmtree(self.ray_temp, ignore_errors=True)
        drop_postgres_database(self.database_url)


@pytest.fixture(scope="module")
def topology(tmp_path_factory):
    if not (BIN / "ray").exists():
        pytest.skip(f"no `ray` command beside {sys.executable}")
    cluster = Topology(tmp_path_factory.mktemp("topology"))
    try:
        cluster.up()
        with cluster.client() as api:
            scene = api.post("/v1/scenes/synthetic", json={"preset": "tiny", "seed": 0}).json()
            while scene["state"] == "generating":
                time.sleep(0.3)
                scene = api.get(f"/v1/scenes/{scene['id']}").json()
            assert scene["state"] == "ready", scene
            cluster.scene = scene["id"]
        yield cluster
    finally:
        cluster.down()


def wait_for(api: httpx.Client, job_id: int, done) -> dict:
    return wait_for_job(api, job_id, done, timeout=400)


def main_steps(api: httpx.Client, job_id: int) -> list[int]:
    return steps_of(api, job_id, "main")


def all_artifacts_intact(api: httpx.Client, job_id: int) -> set[str]:
    artifacts = api.get(f"/v1/jobs/{job_id}/artifacts").json()
    for artifact in artifacts:
        content = api.get(artifact["url"]).content
        assert hashlib.sha256(content).hexdigest() == artifact["sha256"], artifact["name"]
    return {a["name"] for a in artifacts}


def test_every_route_wants_the_token_and_ray_wants_its_own(topology):
    assert httpx.get(f"{topology.url}/v1/jobs").status_code == 401
    assert (
        httpx.get(f"{topology.url}/v1/jobs", headers={"Authorization": "Bearer wrong"}).status_code
        == 401
    )
    ready = httpx.get(f"{topology.url}/readyz").json()
    # reached with the Ray token
    assert ready == {"ready": True, "checks": {"database": "up", "ray": "up"}}
    # Ray's own API, without its token
    refused = httpx.get(f"http://127.0.0.1:{topology.dashboard}/api/jobs/")
    assert refused.status_code in (401, 403)


def test_a_smoke_job_runs_end_to_end_through_leco_submit(topology):
    # --token=VALUE: a random token may start with "-", which argparse would read as an option
    done = topology.run(
        sys.executable,
        "-m",
        "cli",
        "submit",
        "--url",
        topology.url,
        f"--token={topology.token}",
        "--scene",
        str(topology.scene),
        "--method",
        "leco",
        "--profile",
        "smoke",
        "--workers",
        "2",
        timeout=400,
    )
    result = json.loads(done.stdout)
    assert result["state"] == "succeeded", result
    assert result["summary"]["steps"]["total"] == 40 and result["summary"]["method"] == "leco"
    with topology.client() as api:
        job = api.get(f"/v1/jobs/{result['job']}").json()
        assert job["attempts"] == 1 and [p["state"] for p in job["phases"]] == [
            "succeeded",
            "succeeded",
        ]
        names = all_artifacts_intact(api, job["id"])
    assert {"summary.json", "final/models.pt", "final/occupancy.pt", "occupancy.ply"} <= names
    # Both ranks, on the Ray worker node, read one pixel cache per split from the data volume (what
    # the dispatcher passes as LECO_PIXEL_CACHE), whole and finished: one build, shared.
    stores = sorted(p.name for p in (topology.data / "pixel-cache").iterdir() if p.is_dir())
    assert [name.rsplit("-", 2)[1:] for name in stores] == [["train", "x1"], ["val", "x1"]], stores
    for name in stores:
        manifest = json.loads((topology.data / "pixel-cache" / name / "manifest.json").read_text())
        assert (topology.data / "pixel-cache" / name / "pixels.u8").stat().st_size == 3 * sum(
            h * w for h, w in manifest["sizes"]
        )
    # Ray's own CLI, in a process of its own with the cluster's token (Ray reads its auth mode once
    # per process). The job's row is final before its Ray driver process exits, so Ray may still say
    # RUNNING for a moment.
    ray_job = f"leco-job-{job['id']}-attempt-1"
    deadline = time.monotonic() + 60
    while True:
        status = topology.run(
            str(BIN / "ray"),
            "job",
            "status",
            "--address",
            topology.env["LECO_RAY_JOBS_ADDRESS"],
            ray_job,
        )
        plain = re.sub(r"\x1b\[[0-9;]*m", "", status.stdout + status.stderr)
        if "RUNNING" not in plain or time.monotonic() > deadline:
            break
        time.sleep(1)
    assert f"'{ray_job}' succeeded" in plain, plain
    # the job's own process (python -m service.execute) said how its attempt ended, in Ray's log
    logs = topology.run(
        str(BIN / "ray"), "job", "logs", "--address", topology.env["LECO_RAY_JOBS_ADDRESS"], ray_job
    )
    assert f"job {job['id']} attempt 1: succeeded" in logs.stdout + logs.stderr


def submit_long(api: httpx.Client, topology: Topology) -> int:
    body = {
        "scene": topology.scene,
        "method": "switch",
        "profile": "smoke",
        "workers": 2,
        "metrics_every": 10,
        "checkpoint_every": 50,
        "overrides": {"main_steps": 300},
    }
    return api.post("/v1/jobs", json=body).json()["id"]


def test_a_ray_worker_killed_mid_phase_resumes_from_its_checkpoint(topology):
    with topology.client() as api:
        job_id = submit_long(api, topology)
        pid_file = topology.data / "runs" / f"job-{job_id}" / "attempt-1" / "workers" / "rank1.pid"
        job = wait_for(api, job_id, lambda j: j["step"] >= 70 and pid_file.exists())
        killed = int(pid_file.read_text())
        os.kill(killed, signal.SIGKILL)  # a Ray train worker dies mid-phase
        job = wait_for(api, job_id, lambda j: j["state"] in TERMINAL)
        assert job["state"] == "succeeded", job["error"]
        assert job["attempts"] == 1  # Ray Train restarted the worker group inside the same attempt
        assert int(pid_file.read_text()) != killed
        assert main_steps(api, job_id) == list(range(10, 301, 10))  # no gap, no duplicate
        summary = next(
            a for a in api.get(f"/v1/jobs/{job_id}/artifacts").json() if a["name"] == "summary.json"
        )
        assert json.loads(api.get(summary["url"]).content)["steps"]["total"] == 300
        assert "final/models.pt" in all_artifacts_intact(api, job_id)


def test_the_api_restarted_mid_job_loses_nothing_and_pollers_recover(topology):
    with topology.client() as api:
        job_id = submit_long(api, topology)
        wait_for(api, job_id, lambda j: j["step"] >= 40)
    # A dashboard-like poller (job + new metrics every 0.2 s) and the real `leco submit` follower
    # meanwhile.
    seen = {"errors": 0, "ok_after_restart": 0, "steps": [], "last": None}
    restarted, stop = threading.Event(), threading.Event()

    def poll():  # until it has seen the job end and fetched the metrics after that
        after, ended = 0, False
        with httpx.Client(
            base_url=topology.url, headers={"Authorization": f"Bearer {topology.token}"}, timeout=5
        ) as client:
            while not stop.is_set():
                try:
                    seen["last"] = client.get(f"/v1/jobs/{job_id}").raise_for_status().json()
                    got = client.get(
                        f"/v1/jobs/{job_id}/metrics", params={"after_step": after, "name": "loss"}
                    )
                    points = [
                        p["step"]
                        for s in got.raise_for_status().json()["series"]
                        for p in s["points"]
                    ]
                    seen["steps"] += points
                    after = max(points, default=after)
                    seen["ok_after_restart"] += restarted.is_set()
                    if ended:
                        return
                    ended = seen["last"]["state"] in TERMINAL
                except httpx.HTTPError:
                    seen["errors"] += 1
                time.sleep(0.2)

    poller = threading.Thread(target=poll, daemon=True)
    poller.start()
    follower = subprocess.Popen(
        [sys.executable, "-c", FOLLOW, topology.url, topology.token, str(job_id)],
        env=topology.env,
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    time.sleep(2)
    topology.kill("api")
    time.sleep(2)  # the API is down for a while: requests fail to connect
    topology.start_api()
    restarted.set()
    out, err = follower.communicate(timeout=400)
    poller.join(60)
    stop.set()
    assert follower.returncode == 0, err[-2000:]
    assert json.loads(out)["state"] == "succeeded"  # the follower rode the restart out
    # the poller saw the outage and recovered
    assert seen["errors"] > 0 and seen["ok_after_restart"] > 0
    assert seen["last"]["state"] == "succeeded"
    # every step once, in order
    assert sorted(set(seen["steps"])) == seen["steps"] == list(range(10, 301, 10))
    with topology.client() as api:
        job = api.get(f"/v1/jobs/{job_id}").json()
        assert job["state"] == "succeeded" and job["attempts"] == 1
        assert main_steps(api, job_id) == list(range(10, 301, 10))
        assert {"summary.json", "final/models.pt"} <= all_artifacts_intact(api, job_id)


def test_a_dispatcher_stopped_mid_job_hands_it_back_and_the_next_one_resumes_it(topology):
    """`docker stop` on the dispatcher: SIGTERM to its main process only. The job goes back to the
    queue at once (not failed, not waiting for a lease to expire), its run checkpoints and stops,
    and a new dispatcher resumes it from there."""
    with topology.client() as api:
        job_id = submit_long(api, topology)
        wait_for(api, job_id, lambda j: j["step"] >= 80)
        dispatcher = topology.processes.pop("dispatcher")
        started = time.monotonic()
        dispatcher.send_signal(signal.SIGTERM)
        dispatcher.wait(60)
        assert time.monotonic() - started < 40  # within a compose stop_grace_period
        job = api.get(f"/v1/jobs/{job_id}").json()
        assert job["state"] == "queued" and job["attempts"] == 1, job
        assert (
            "its dispatcher" in job["error"] and "resumes from its last checkpoint" in job["error"]
        )
        topology.start("dispatcher", "dispatch", "--slots", "1")
        job = wait_for(api, job_id, lambda j: j["state"] in TERMINAL)
        assert job["state"] == "succeeded" and job["attempts"] == 2, job
        assert main_steps(api, job_id) == list(range(10, 301, 10))  # no gap, no duplicate
        assert "final/models.pt" in all_artifacts_intact(api, job_id)


# `leco submit`'s own follower (cli.submit.follow through Api.call, which retries while the API
# restarts).
FOLLOW = """
import json, sys
from cli.submit import Api, follow
job = follow(Api(sys.argv[1], sys.argv[2]), int(sys.argv[3]), sys.stderr, poll_s=0.5)
print(json.dumps({"state": job["state"]}))
"""


def test_no_log_holds_a_token(topology):
    """Last: after every test above (refusals, a job, a worker killed, an API restart), plus a few
    more refused and failing requests, neither the API token nor Ray's appears in any log of the
    topology."""
    with topology.client() as api:
        assert api.get("/v1/jobs/999999").status_code == 404
        assert (
            api.post("/v1/jobs", json={"scene": topology.scene, "method": "nope"}).status_code
            == 422
        )
    # near misses
    for header in (topology.token, f"Bearer {topology.token}x", f"Basic {topology.token}"):
        assert (
            httpx.get(f"{topology.url}/v1/jobs", headers={"Authorization": header}).status_code
            == 401
        )
    logs = [p for p in topology.logs.rglob("*") if p.is_file()]
    logs += [
        p
        for p in topology.ray_temp.rglob("*")
        if p.is_file() and p.suffix in (".log", ".out", ".err")
    ]
    assert len(logs) > 5
    for path in logs:
        text = path.read_text(errors="replace")
        assert topology.token not in text, f"the API token is in {path}"
        if path.parent == topology.logs:
            assert topology.env["RAY_AUTH_TOKEN"] not in text, f"Ray's token is in {path}"

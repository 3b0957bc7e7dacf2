"""Helpers several test folders share: the repository root, a client of the API as a user holds one,
and waiting on the service's scenes and jobs. Fixtures live in conftest.py."""

from __future__ import annotations

import io
import itertools
import os
import signal
import subprocess
import sys
import tarfile
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

import pytest

ROOT = Path(__file__).resolve().parents[1]

# A job trained, rendered or faulted end to end through the service runs on one database: the code
# it exercises is the same on both, and what the database itself does (claims, leases, outages,
# every query of the API and the queue) is tested on both. SQLite is `make run`'s; PostgreSQL is
# deployed, where several dispatchers share the queue (the lease tests run there).
ON_SQLITE = pytest.mark.parametrize("database_url", ["sqlite"], indirect=True)
ON_POSTGRESQL = pytest.mark.parametrize("database_url", ["postgresql"], indirect=True)


@contextmanager
def api_client(settings, token: str | None = None) -> Iterator:
    """The API app on `settings` in a TestClient (with `token` as its bearer, when given); the
    client carries the settings it was made with as `.settings`."""
    from fastapi.testclient import TestClient

    from service.api.app import create_app

    headers = {"Authorization": f"Bearer {token}"} if token else {}
    with TestClient(create_app(settings), headers=headers) as client:
        client.settings = settings
        yield client


def synthetic_scene(api, timeout: float = 60) -> dict:
    """The tiny synthetic city registered through the API, once it is ready (its scene row)."""
    scene = api.post("/v1/scenes/synthetic", json={"preset": "tiny", "seed": 0}).json()
    deadline = time.monotonic() + timeout
    while scene["state"] == "generating" and time.monotonic() < deadline:
        time.sleep(0.2)
        scene = api.get(f"/v1/scenes/{scene['id']}").json()
    assert scene["state"] == "ready", scene
    return scene


def ready_scene(api) -> int:
    """synthetic_scene's id."""
    return synthetic_scene(api)["id"]


def wait_for(api, job_id: int, done: Callable[[dict], bool], timeout: float = 240) -> dict:
    """Polls the job until `done(job)`; fails naming the job's last state after `timeout`."""
    deadline = time.monotonic() + timeout
    job: dict = {}
    while time.monotonic() < deadline:
        job = api.get(f"/v1/jobs/{job_id}").json()
        if done(job):
            return job
        time.sleep(0.3)
    raise AssertionError(f"job {job_id} never got there: {job}")


def attempt_processes(job_id: int, attempt: int | None = None) -> list[int]:
    """Pids of the child processes running the job's attempt (`python -m service.execute`), found
    in /proc."""
    wanted = {"--job-id": str(job_id)}
    if attempt is not None:
        wanted["--attempt"] = str(attempt)
    pids = []
    for entry in Path("/proc").iterdir():
        try:
            words = (entry / "cmdline").read_bytes().decode().split("\0")
        except (OSError, ValueError):  # not a process, or gone meanwhile
            continue
        given = dict(zip(words, words[1:]))
        if "service.execute" in words and all(given.get(k) == v for k, v in wanted.items()):
            pids.append(int(entry.name))
    return pids


def steps_of(api, job_id: int, phase: str, name: str = "loss") -> list[int]:
    """The steps at which the job stored metric `name` in `phase`."""
    params = {"phase": phase, "name": name}
    series = api.get(f"/v1/jobs/{job_id}/metrics", params=params).json()["series"]
    return [p["step"] for p in series[0]["points"]] if series else []


def tar_of(folder, top: str = "scene") -> bytes:
    """A folder as a .tar.gz upload with `top` as its one top-level folder."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tf:
        tf.add(folder, arcname=top)
    return buffer.getvalue()


_HANDED_OUT: set[int] = set()


def free_port() -> int:
    """A free TCP port on the loopback interface, for a server a test starts. Never one it handed
    out before in this process: the kernel may give a just-closed port again, and two servers of
    one test (Ray's GCS and its dashboard) must not be told the same port."""
    import socket

    while True:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        if port not in _HANDED_OUT:
            _HANDED_OUT.add(port)
            return port


PG_ADMIN = "host=127.0.0.1 port=5432 user=postgres dbname=postgres"


def fresh_postgres_database() -> str:
    """A new, empty database on 127.0.0.1:5432; skips (saying why) when no server answers there."""
    import os

    try:
        import psycopg

        with psycopg.connect(PG_ADMIN, autocommit=True, connect_timeout=3) as conn:
            name = f"leco_test_{os.getpid()}_{next(_pg_counter)}"
            conn.execute(f"DROP DATABASE IF EXISTS {name} WITH (FORCE)")
            conn.execute(f"CREATE DATABASE {name}")
    except Exception as error:  # no server: the SQLite half of the tests still runs
        pytest.skip(f"PostgreSQL at 127.0.0.1:5432 not available ({type(error).__name__}: {error})")
    return f"postgresql+psycopg://postgres@127.0.0.1:5432/{name}"


def drop_postgres_database(url: str) -> None:
    import psycopg

    from service.db import engine_for

    engine_for(url).dispose()
    with psycopg.connect(PG_ADMIN, autocommit=True) as conn:
        conn.execute(f"DROP DATABASE IF EXISTS {url.rsplit('/', 1)[1]} WITH (FORCE)")


_pg_counter = itertools.count()


@contextmanager
def uvicorn_in_thread(app, **config):
    """A real uvicorn server for `app` on a free loopback port, in a thread; yields the port."""
    import uvicorn

    port = free_port()
    runner = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, **config))
    thread = threading.Thread(target=runner.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not runner.started and time.monotonic() < deadline:
        time.sleep(0.05)
    assert runner.started
    try:
        yield port
    finally:
        runner.should_exit = True
        thread.join(10)


@contextmanager
def dispatch_process(settings, **env: str) -> Iterator[subprocess.Popen]:
    """`leco dispatch` in a process (and session) of its own with a 4 s lease, to be killed mid-job
    with SIGKILL; on leaving, its whole process group is killed (a dead dispatcher's Ray agents
    outlive it in its group: cleared, as a container stop would)."""
    process = subprocess.Popen(
        [sys.executable, "-m", "cli", "dispatch"],
        cwd=ROOT,
        env={
            **os.environ,
            "DATABASE_URL": settings.db_url,
            "LECO_DATA_DIR": str(settings.data_dir),
            "LECO_LEASE_S": "4",
            "LECO_LOCAL_CPUS": "2",
            "RAY_ADDRESS": "",
            **env,
        },
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        yield process
    finally:
        try:
            os.killpg(process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass

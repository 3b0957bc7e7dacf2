"""Faults in the service, each ending with a check that nothing was lost: the database going away
mid-job (PostgreSQL refusing connections and dropping the open ones), the artifact root full (a real
256 KiB tmpfs) or unwritable, a job whose losses go non-finite, and the database away in the middle
of a render or an export (the other job kinds). The job runs on a local Ray (2 CPU workers) under a
dispatcher thread, as `leco serve` runs it."""

import subprocess
import threading
import time
from pathlib import Path

import psycopg
import pytest
import torch
from fastapi.testclient import TestClient
from sqlalchemy import select

from service.api.app import create_app
from service.db import reading, upgrade
from service.dispatcher import Dispatcher
from service.settings import Settings
from service.store import ArtifactStore
from service.tables import Artifact
from tests.helpers import (
    ON_SQLITE,
    PG_ADMIN,
    drop_postgres_database,
    fresh_postgres_database,
    ready_scene,
    steps_of,
    wait_for,
)

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("local_ray")]


def run_service(settings: Settings):
    """The API (in-process) and a dispatcher thread on `settings`; returns (client, dispatcher,
    thread)."""
    client = TestClient(create_app(settings))
    client.__enter__()
    dispatcher = Dispatcher(settings, poll_s=0.2)
    thread = threading.Thread(target=dispatcher.run_forever, daemon=True)
    thread.start()
    return client, dispatcher, thread


def submit_switch(api, **config) -> int:
    """A Switch-NeRF smoke job on two Ray workers on the tiny city, with `config` on top; returns
    its id."""
    body = {
        "scene": ready_scene(api),
        "method": "switch",
        "profile": "smoke",
        "workers": 2,
        **config,
    }
    return api.post("/v1/jobs", json=body).json()["id"]


def assert_store_consistent(settings: Settings, *job_ids: int) -> list[dict]:
    """Every artifact row of these jobs (the store's only ones) has its bytes (sha256 checked), no
    blob is unreferenced, nothing is half-staged."""
    store = ArtifactStore(settings.db_url, settings.artifacts)
    with reading(settings.db_url) as session:
        rows = session.scalars(select(Artifact).where(Artifact.job_id.in_(job_ids))).all()
        metas = [{"id": r.id, "name": r.name, "sha256": r.sha256, "size": r.size} for r in rows]
    for meta in metas:
        store.verified_path(meta)
    files = [p for p in settings.artifacts.rglob("*") if p.is_file()]
    assert [p for p in files if p.parent.name == "tmp"] == []  # no half-written upload left behind
    assert {p.name for p in files} == {m["sha256"] for m in metas}  # no orphan blob
    return metas


# ----- the database away for a while
# -------------------------------------------------------------------------
def block_connections(url: str, blocked: bool) -> None:
    """PostgreSQL stops accepting connections to this database and drops the open ones (or accepts
    again)."""
    name = url.rsplit("/", 1)[1]
    with psycopg.connect(PG_ADMIN, autocommit=True) as conn:
        conn.execute(f"ALTER DATABASE {name} ALLOW_CONNECTIONS {'false' if blocked else 'true'}")
        if blocked:
            conn.execute(
                "SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = %s", (name,)
            )


def test_a_database_outage_pauses_the_job_and_loses_nothing(tmp_path):
    url = fresh_postgres_database()
    settings = Settings(data_dir=tmp_path / "data", database_url=url, local_cpus=2, lease_s=40.0)
    upgrade(url)
    api, dispatcher, thread = run_service(settings)
    try:
        job_id = submit_switch(
            api, metrics_every=10, checkpoint_every=50, overrides={"main_steps": 200}
        )
        wait_for(api, job_id, lambda j: j["step"] >= 40)
        block_connections(url, True)
        try:
            time.sleep(1.0)
            during = api.get(f"/v1/jobs/{job_id}")
            assert during.status_code == 503 and during.headers["retry-after"] == "2"
            assert (
                "database is unavailable" in during.json()["detail"]
                and "Traceback" not in during.text
            )
            # longer than the dispatcher's heartbeat period (lease / 4) and many metric steps
            time.sleep(7.0)
        finally:
            block_connections(url, False)
        job = wait_for(api, job_id, lambda j: j["state"] in ("succeeded", "failed"), timeout=300)
        assert job["state"] == "succeeded", job["error"]
        assert job["attempts"] == 1  # the writes waited for the database; the lease was never lost
        # no metric dropped or duplicated
        assert steps_of(api, job_id, "main") == list(range(10, 201, 10))
        assert thread.is_alive()  # the dispatcher rode the outage out (no crash, no restart)
        names = {m["name"] for m in assert_store_consistent(settings, job_id)}
        assert {"summary.json", "final/models.pt", "metrics.jsonl"} <= names
    finally:
        dispatcher.stop(wait=True)
        api.__exit__(None, None, None)
        drop_postgres_database(url)


# ----- the artifact root full or unwritable
# --------------------------------------------------------------------
@pytest.fixture
def tiny_disk(tmp_path):
    """A real 256 KiB filesystem (tmpfs): writes past it fail with ENOSPC."""
    mount = tmp_path / "small-disk"
    mount.mkdir()
    made = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mount)],
        capture_output=True,
        text=True,
    )
    if made.returncode != 0:
        pytest.skip(
            f"cannot mount a small tmpfs here (needs root or CAP_SYS_ADMIN): {made.stderr.strip()}"
        )
    yield mount
    subprocess.run(["umount", "-l", str(mount)], check=False)


@ON_SQLITE
@pytest.mark.parametrize("fault", ["disk full", "unwritable"])
def test_a_failing_artifact_root_fails_the_job_with_that_reason(
    fault, service_settings, tmp_path, request
):
    if fault == "disk full":
        root, expected = (
            request.getfixturevalue("tiny_disk") / "artifacts",
            "No space left on device",
        )
    else:
        blocker = tmp_path / "a-file"
        blocker.write_text("a file where the artifact root's folder should be")
        root, expected = blocker / "artifacts", "is not writable"
    settings = Settings(**{**service_settings.model_dump(), "artifact_root": root})
    api, dispatcher, thread = run_service(settings)
    try:
        job_id = submit_switch(
            api, metrics_every=5, checkpoint_every=10, overrides={"main_steps": 60}
        )
        job = wait_for(api, job_id, lambda j: j["state"] in ("succeeded", "failed"), timeout=300)
        assert job["state"] == "failed" and job["attempts"] == 1
        assert expected in job["error"] and "could not be written" in job["error"], job["error"]
        assert str(settings.artifacts) in job["error"]  # names where
        assert "Traceback" not in job["error"]
        steps = steps_of(api, job_id, "main")
        # it stopped at a step boundary
        assert steps == list(range(5, steps[-1] + 1, 5)) and 10 <= steps[-1] < 60
        if fault == "disk full":
            # what did fit is whole; no partial or orphan blob
            kept = assert_store_consistent(settings, job_id)
            assert any(m["name"].startswith("checkpoint-") for m in kept)
        else:
            assert api.get(f"/v1/jobs/{job_id}/artifacts").json() == []
        assert thread.is_alive()
    finally:
        dispatcher.stop(wait=True)
        api.__exit__(None, None, None)


@ON_SQLITE
# ----- losses that go non-finite
# -------------------------------------------------------------------------------
def test_repeated_non_finite_losses_fail_the_job_and_keep_its_last_good_checkpoint(
    service_settings,
):
    api, dispatcher, thread = run_service(service_settings)
    try:
        # A learning rate of 1e6 (the schema's largest) blows the weights up in a step or two: every
        # later loss is non-finite.
        job_id = submit_switch(
            api,
            metrics_every=1,
            checkpoint_every=1,
            max_nonfinite_steps=5,
            overrides={"main_steps": 200, "lr": 1e6, "lr_final": 1e6},
        )
        job = wait_for(api, job_id, lambda j: j["state"] in ("succeeded", "failed"), timeout=300)
        # not retried: a retry would only repeat it
        assert job["state"] == "failed" and job["attempts"] == 1
        assert "5 consecutive steps had a non-finite loss or gradient" in job["error"]
        assert "Lower the learning rate" in job["error"]
        assert job["step"] < 20
        checkpoints = api.get(f"/v1/jobs/{job_id}/artifacts", params={"kind": "checkpoint"}).json()
        assert checkpoints, "the last good checkpoint was not kept"
        newest = max(checkpoints, key=lambda a: a["step"])
        path = Path(service_settings.data_dir) / "newest.pt"
        path.write_bytes(api.get(newest["url"]).content)
        state = torch.load(path, weights_only=False)
        assert all(
            torch.isfinite(v).all() for v in state["models"].values() if v.is_floating_point()
        )
        assert_store_consistent(service_settings, job_id)
    finally:
        dispatcher.stop(wait=True)
        api.__exit__(None, None, None)


# ----- the database away during the other job kinds: mid-render, and while an export waits
# -------------------------------------------------------------------------------------------------
def trained_parent(api) -> int:
    parent = submit_switch(api, workers=1, overrides={"main_steps": 20})
    done = wait_for(api, parent, lambda j: j["state"] in ("succeeded", "failed"))
    assert done["state"] == "succeeded", done["error"]
    return parent


def test_a_database_outage_mid_render_pauses_it_and_loses_nothing(tmp_path):
    url = fresh_postgres_database()
    settings = Settings(
        data_dir=tmp_path / "data", database_url=url, local_cpus=2, lease_s=40.0, backend="local"
    )
    upgrade(url)
    api, dispatcher, thread = run_service(settings)
    try:
        parent = trained_parent(api)
        render = {"frames": 40, "width": 160, "height": 120}
        job_id = api.post(f"/v1/jobs/{parent}/renders", json=render).json()["id"]
        running = wait_for(api, job_id, lambda j: j["step"] >= 1, timeout=60)
        block_connections(url, True)
        try:
            time.sleep(6.0)  # longer than the dispatcher's heartbeat period (lease / 4)
        finally:
            block_connections(url, False)
        assert running["state"] == "running" and running["step"] < 40
        job = wait_for(api, job_id, lambda j: j["state"] in ("succeeded", "failed"), timeout=300)
        assert job["state"] == "succeeded", job["error"]
        assert job["attempts"] == 1  # its writes waited for the database; the lease held
        assert thread.is_alive()
        names = [m["name"] for m in assert_store_consistent(settings, parent, job_id)]
        assert names.count("video.mp4") == 1
    finally:
        dispatcher.stop(wait=True)
        api.__exit__(None, None, None)
        drop_postgres_database(url)


def test_a_database_outage_while_an_export_waits_delays_it_and_loses_nothing(tmp_path):
    """An export takes a second on the tiny city, too short to catch mid-way: the database goes
    away while it is queued and a dispatcher starts, which then claims and runs it."""
    url = fresh_postgres_database()
    settings = Settings(
        data_dir=tmp_path / "data", database_url=url, local_cpus=2, lease_s=40.0, backend="local"
    )
    upgrade(url)
    api, dispatcher, thread = run_service(settings)
    try:
        parent = trained_parent(api)
        dispatcher.stop(wait=True)
        body = {"what": "pointcloud", "stride": 1, "min_opacity": 0.0}
        job_id = api.post(f"/v1/jobs/{parent}/exports", json=body).json()["id"]
        block_connections(url, True)
        try:
            dispatcher = Dispatcher(settings, poll_s=0.2)
            thread = threading.Thread(target=dispatcher.run_forever, daemon=True)
            thread.start()
            time.sleep(6.0)
            assert thread.is_alive()  # it rides the outage out from its first poll
        finally:
            block_connections(url, False)
        job = wait_for(api, job_id, lambda j: j["state"] in ("succeeded", "failed"), timeout=300)
        assert job["state"] == "succeeded", job["error"]
        assert job["attempts"] == 1
        names = [m["name"] for m in assert_store_consistent(settings, parent, job_id)]
        assert {"pointcloud.ply", "transform.json", "export.json"} <= set(names)
        assert names.count("pointcloud.ply") == 1
    finally:
        dispatcher.stop(wait=True)
        api.__exit__(None, None, None)
        drop_postgres_database(url)

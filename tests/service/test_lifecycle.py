"""The whole job lifecycle on a local Ray (2 CPU workers), on SQLite and on PostgreSQL: a smoke job
from submission to downloaded artifacts, a cancel while running, and a dispatcher killed mid-job
whose lease expires and whose job resumes from its checkpoint and finishes once."""

import hashlib
import json
import os
import signal
import threading
import time

import pytest
from sqlalchemy import select

from service.db import reading
from service.dispatcher import Dispatcher
from service.tables import Artifact
from tests.helpers import (
    ON_POSTGRESQL,
    ON_SQLITE,
    api_client,
    attempt_processes,
    dispatch_process,
    ready_scene,
    steps_of,
    wait_for,
)

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("local_ray")]


@pytest.fixture
def api(service_settings):
    with api_client(service_settings) as client:
        yield client


@pytest.fixture
def dispatcher(service_settings):
    running = Dispatcher(service_settings, poll_s=0.2)
    thread = threading.Thread(target=running.run_forever, daemon=True)
    yield running, thread
    running.stop(wait=True)


# on PostgreSQL the same path runs through `leco submit` in tests/service/test_topology.py
@ON_SQLITE
def test_a_smoke_job_runs_from_submission_to_artifacts(api, dispatcher):
    scene = ready_scene(api)
    body = {
        "scene": scene,
        "method": "leco",
        "profile": "smoke",
        "workers": 2,
        "metrics_every": 5,
        "checkpoint_every": 20,
        "val_every": 20,
    }
    job = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": "life"}).json()
    dispatcher[1].start()
    job = wait_for(api, job["id"], lambda j: j["state"] in ("succeeded", "failed", "cancelled"))
    assert job["state"] == "succeeded", job["error"]
    assert job["attempts"] == 1 and job["step"] == 40 and job["percent"] == 100.0
    assert [(p["name"], p["state"]) for p in job["phases"]] == [
        ("occupancy", "succeeded"),
        ("main", "succeeded"),
    ]
    assert steps_of(api, job["id"], "occupancy") == [5, 10, 15, 20]
    assert steps_of(api, job["id"], "main") == [25, 30, 35, 40]
    assert 0 <= job["latest_metrics"]["occupancy"]["fraction_empty"] <= 1
    artifacts = api.get(f"/v1/jobs/{job['id']}/artifacts").json()
    kinds = {a["kind"] for a in artifacts}
    assert kinds == {"checkpoint", "render", "occupancy_model", "pointcloud", "report"}
    # older ones pruned
    assert len([a for a in artifacts if a["name"].startswith("checkpoint-")]) <= 2
    for artifact in artifacts:
        content = api.get(artifact["url"]).content
        assert (
            hashlib.sha256(content).hexdigest() == artifact["sha256"]
            and len(content) == artifact["size"]
        )
    summary = json.loads(
        api.get(next(a["url"] for a in artifacts if a["name"] == "summary.json")).content
    )
    assert (
        summary["method"] == "leco"
        and summary["world_size"] == 2
        and summary["steps"]["total"] == 40
    )
    occupancy = next(a for a in artifacts if a["kind"] == "occupancy_model")
    assert occupancy["name"] == "final/occupancy.pt" and occupancy["size"] > 1000
    # the replayed submit returns the same job; nothing new was queued
    again = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": "life"}).json()
    assert again["id"] == job["id"] and api.get("/v1/jobs").json()["total"] == 1


@ON_SQLITE
def test_cancel_while_running_stops_at_a_step_boundary_and_keeps_what_it_stored(api, dispatcher):
    scene = ready_scene(api)
    body = {
        "scene": scene,
        "method": "switch",
        "profile": "smoke",
        "workers": 2,
        "metrics_every": 5,
        "checkpoint_every": 1000,
        "overrides": {"main_steps": 5000},
    }
    job = api.post("/v1/jobs", json=body).json()
    dispatcher[1].start()
    wait_for(api, job["id"], lambda j: j["step"] >= 30)
    assert api.post(f"/v1/jobs/{job['id']}/cancel").json()["cancel_requested"]
    job = wait_for(api, job["id"], lambda j: j["state"] != "running", timeout=60)
    assert job["state"] == "cancelled" and 30 <= job["step"] < 5000
    assert {p["state"] for p in job["phases"]} == {"cancelled"}
    steps = steps_of(api, job["id"], "main")
    assert steps == list(range(5, steps[-1] + 1, 5)) and steps[-1] >= 30
    checkpoints = api.get(f"/v1/jobs/{job['id']}/artifacts", params={"kind": "checkpoint"}).json()
    assert len(checkpoints) == 1 and checkpoints[0]["step"] >= steps[-1]  # the stop wrote one
    assert api.post(f"/v1/jobs/{job['id']}/cancel").json()["state"] == "cancelled"


@ON_POSTGRESQL
def test_a_killed_dispatcher_loses_its_lease_and_the_job_resumes_once(api, service_settings):
    scene = ready_scene(api)
    body = {
        "scene": scene,
        "method": "switch",
        "profile": "smoke",
        "workers": 2,
        "metrics_every": 10,
        "checkpoint_every": 50,
        "overrides": {"main_steps": 300},
    }
    job_id = api.post("/v1/jobs", json=body).json()["id"]
    with dispatch_process(service_settings) as first:
        killed_at = wait_for(api, job_id, lambda j: j["step"] >= 70)["step"]
        os.kill(first.pid, signal.SIGKILL)  # the dispatcher, with its local Ray, dies mid-job
        first.wait(10)
    assert killed_at < 300
    second = Dispatcher(service_settings, poll_s=0.2)
    thread = threading.Thread(target=second.run_forever, daemon=True)
    thread.start()
    try:
        job = wait_for(api, job_id, lambda j: j["state"] in ("succeeded", "failed"), timeout=300)
    finally:
        second.stop(wait=True)
    assert job["state"] == "succeeded", job["error"]
    assert job["attempts"] == 2  # the expired lease put it back in the queue once
    steps = steps_of(api, job_id, "main")
    assert steps == list(range(10, 301, 10))  # no gap, no duplicate across the two attempts
    summary = next(
        a for a in api.get(f"/v1/jobs/{job_id}/artifacts").json() if a["name"] == "summary.json"
    )
    assert json.loads(api.get(summary["url"]).content)["steps"]["total"] == 300


@ON_SQLITE
def test_a_dispatcher_killed_mid_render_hands_it_back_and_one_video_is_stored(service_settings):
    """The render kind under the same fault as training: SIGKILL mid-attempt, the lease expires,
    the next attempt renders again and stores the one video."""
    settings = service_settings.model_copy(update={"backend": "local"})
    with api_client(settings) as api:
        body = {"scene": ready_scene(api), "method": "switch", "profile": "smoke"}
        parent = api.post("/v1/jobs", json={**body, "overrides": {"main_steps": 10}}).json()["id"]
        trainer = Dispatcher(settings, poll_s=0.2)
        threading.Thread(target=trainer.run_forever, daemon=True).start()
        try:
            done = wait_for(api, parent, lambda j: j["state"] in ("succeeded", "failed"))
            assert done["state"] == "succeeded", done["error"]
        finally:
            trainer.stop(wait=True)
        render = {"frames": 60, "width": 160, "height": 120}
        job_id = api.post(f"/v1/jobs/{parent}/renders", json=render).json()["id"]
        with dispatch_process(settings, LECO_BACKEND="local") as first:
            killed_at = wait_for(api, job_id, lambda j: j["step"] >= 2)["step"]
            assert attempt_processes(job_id, 1)  # the render runs in the dispatcher's child
            os.kill(first.pid, signal.SIGKILL)
            first.wait(10)
            gone_by = time.monotonic() + 10  # it dies with its dispatcher (parent-death signal)
            while attempt_processes(job_id, 1) and time.monotonic() < gone_by:
                time.sleep(0.1)
            assert attempt_processes(job_id, 1) == []
        assert killed_at < 60
        second = Dispatcher(settings, poll_s=0.2)
        threading.Thread(target=second.run_forever, daemon=True).start()
        try:
            job = wait_for(api, job_id, lambda j: j["state"] in ("succeeded", "failed"), 300)
        finally:
            second.stop(wait=True)
        assert job["state"] == "succeeded" and job["attempts"] == 2, job
    with reading(settings.db_url) as session:
        rows = session.execute(
            select(Artifact.attempt).where(Artifact.job_id == job_id, Artifact.name == "video.mp4")
        ).all()
    assert rows == [(2,)]  # stored once, by the attempt that finished

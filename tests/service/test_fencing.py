"""Fencing: every write of a run carries its attempt and is refused once another attempt holds the
job; lease and database-retry settings cannot contradict each other; and a database outage longer
than the lease ends with one writer per step, a gap-free metric series and no duplicate."""

import threading
import time

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from service import queue
from service.api.app import create_app
from service.db import reading, transaction, upgrade
from service.dispatcher import Dispatcher
from service.jobs.kinds import TRAIN
from service.jobs.submit import submit
from service.queue import StaleAttempt
from service.runstore import DatabaseRunStore
from service.settings import Settings
from service.tables import Artifact, JobPhase, Metric, Scene
from workers.config import TrainConfig


def test_a_retry_budget_that_outlives_the_lease_is_refused_at_start_up(monkeypatch):
    # the defaults: a 180 s lease, two thirds of it to ride out an outage
    assert Settings().retry_s == 120.0
    assert Settings(lease_s=6.0).retry_s == 4.0
    with pytest.raises(ValueError, match="shorter than three quarters of LECO_LEASE_S"):
        Settings(lease_s=60.0, db_retry_s=50.0)  # 50 s of waiting > 45 s the lease surely lasts
    monkeypatch.setenv("LECO_LEASE_S", "60")
    monkeypatch.setenv("LECO_DB_RETRY_S", "120")  # a 60-120 s outage splits a job
    with pytest.raises(
        ValueError,
        match=r"invalid service settings: .*LECO_DB_RETRY_S \(120 s\).*LECO_LEASE_S \(60 s",
    ):
        Settings.from_env()
    monkeypatch.setenv("LECO_DB_RETRY_S", "40")
    assert Settings.from_env().retry_s == 40.0


def test_a_ray_job_runs_under_the_lease_and_retry_budget_of_its_dispatcher(monkeypatch, tmp_path):
    from service.dispatcher import cluster_env

    dispatcher = Settings(data_dir=tmp_path, lease_s=30.0)  # as the topology test's dispatcher
    for name, value in cluster_env(dispatcher).items():
        monkeypatch.setenv(name, value)
    job = Settings.from_env()
    assert (job.lease_s, job.retry_s, job.db_url) == (30.0, 20.0, dispatcher.db_url)


def claimed_job(settings: Settings) -> int:
    """A queued smoke job on a scene row, claimed once (attempt 1)."""
    with transaction(settings.db_url) as session:
        scene = Scene(name="fenced", source="synthetic", state="ready", path="/nowhere")
        session.add(scene)
        session.flush()
        job_id = submit(session, TRAIN, scene.id, TrainConfig(method="switch", profile="smoke")).id
    assert queue.claim(settings.db_url, "first", settings.lease_s) == (job_id, 1)
    return job_id


def counts(settings: Settings, job_id: int) -> tuple[int, int]:
    with reading(settings.db_url) as session:
        metrics = session.scalar(
            select(func.count()).select_from(Metric).where(Metric.job_id == job_id)
        )
        artifacts = session.scalar(
            select(func.count()).select_from(Artifact).where(Artifact.job_id == job_id)
        )
    return metrics, artifacts


def test_a_stale_attempt_writes_nothing(service_settings, tmp_path):
    settings = service_settings
    job_id = claimed_job(settings)
    first = DatabaseRunStore(settings.db_url, str(settings.artifacts), job_id, 1, settings.retry_s)
    first.phase_started("main")
    first.write(10, {"phase": "main", "loss": 0.5, "phase_step": 10})
    checkpoint = tmp_path / "state.pt"
    checkpoint.write_bytes(b"attempt one's checkpoint")
    first.artifact(
        "checkpoint", checkpoint, name="checkpoint-step0000010.pt", phase="main", step=10
    )
    # Attempt 1's lease lapses while it still runs (its dispatcher lost the database); attempt 2
    # claims the job.
    assert queue.release(settings.db_url, job_id, 1, "lease expired")
    assert queue.claim(settings.db_url, "second", settings.lease_s) == (job_id, 2)
    before = counts(settings, job_id)
    late = tmp_path / "late.pt"
    late.write_bytes(b"bytes only attempt one ever wrote")
    for write in (
        lambda: first.write(20, {"phase": "main", "loss": 0.1, "phase_step": 20}),
        lambda: first.artifact(
            "checkpoint", late, name="checkpoint-step0000020.pt", phase="main", step=20
        ),
        lambda: first.resume(0),
        lambda: first.phase_started("main"),
    ):
        with pytest.raises(
            StaleAttempt, match="attempt 1 no longer holds job .* \\(attempt 2 does\\)"
        ):
            write()
    assert counts(settings, job_id) == before  # no metric, no artifact row, nothing forgotten
    blobs = {p.name for p in settings.artifacts.rglob("*") if p.is_file()}
    assert len(blobs) == 1  # attempt one's refused blob was collected with its transaction
    assert first.stop_reason() is not None and "attempt 1 no longer holds" in first.stop_reason()
    second = DatabaseRunStore(settings.db_url, str(settings.artifacts), job_id, 2, settings.retry_s)
    second.resume(10)
    second.write(20, {"phase": "main", "loss": 0.2, "phase_step": 20})
    with reading(settings.db_url) as session:
        rows = session.execute(
            select(Metric.step, Metric.attempt).where(
                Metric.job_id == job_id, Metric.name == "loss"
            )
        ).all()
        step = session.scalar(
            select(JobPhase.step).where(JobPhase.job_id == job_id, JobPhase.name == "main")
        )
    assert sorted(rows) == [(10, 1), (20, 2)] and step == 20


# ----- the outage the issue describes, on PostgreSQL
# ----------------------------------------------------------
@pytest.mark.slow
@pytest.mark.usefixtures("local_ray")  # shut down after the module, not left to the next one
def test_an_outage_longer_than_the_lease_leaves_one_writer_and_no_gap(tmp_path):
    from tests.helpers import drop_postgres_database, fresh_postgres_database, steps_of, wait_for
    from tests.service.test_faults import block_connections, submit_switch

    url = fresh_postgres_database()
    upgrade(url)
    # retries 5.3 s
    settings = Settings(data_dir=tmp_path / "data", database_url=url, local_cpus=2, lease_s=8.0)
    client = TestClient(create_app(settings))
    api = client.__enter__()
    dispatcher = Dispatcher(settings, poll_s=0.2)
    thread = threading.Thread(target=dispatcher.run_forever, daemon=True)
    thread.start()
    try:
        job_id = submit_switch(
            api, metrics_every=10, checkpoint_every=50, overrides={"main_steps": 200}
        )
        wait_for(api, job_id, lambda j: j["step"] >= 60)
        block_connections(url, True)
        try:
            # past the retry budget and the lease: attempt 1 must stop before anyone re-claims
            time.sleep(14.0)
        finally:
            block_connections(url, False)
        job = wait_for(api, job_id, lambda j: j["state"] in ("succeeded", "failed"), timeout=300)
        assert job["state"] == "succeeded", job["error"]
        assert job["attempts"] == 2
        assert steps_of(api, job_id, "main") == list(range(10, 201, 10))  # gap-free, each step once
        with reading(url) as session:
            writers = session.execute(
                select(Metric.step, Metric.attempt).where(
                    Metric.job_id == job_id, Metric.name == "loss"
                )
            ).all()
            resumed_at = session.scalar(
                select(func.min(Metric.step)).where(Metric.job_id == job_id, Metric.attempt == 2)
            )
            artifacts = session.execute(
                select(Artifact.name, Artifact.attempt).where(Artifact.job_id == job_id)
            ).all()
        # One writer per step: attempt 1 up to its last stored checkpoint, attempt 2 after it, never
        # interleaved.
        assert {a for _, a in writers} == {1, 2}
        assert all((a == 1) == (s < resumed_at) for s, a in writers), sorted(writers)
        assert {a for name, a in artifacts if not name.startswith("checkpoint")} == {2}
        folders = sorted(p.name for p in (settings.runs_dir / f"job-{job_id}").iterdir())
        assert folders == ["attempt-1", "attempt-2"]  # each attempt trained in its own folder
    finally:
        dispatcher.stop(wait=True)
        client.__exit__(None, None, None)
        drop_postgres_database(url)

"""The database layer on SQLite and PostgreSQL: migrations, schema check, the queue's transitions,
and claims that never hand one job to two dispatchers."""

import threading
from datetime import timedelta

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import inspect, select, update

from service import queue
from service.db import (
    SchemaError,
    alembic_config,
    check_schema,
    current_revision,
    engine_for,
    head_revision,
    transaction,
    upgrade,
)
from service.jobs.kinds import TRAIN
from service.jobs.submit import submit
from service.tables import Artifact, Base, Job, JobPhase, Scene, utcnow
from workers.config import TrainConfig


def add_scene(url, name="s", state="ready") -> int:
    with transaction(url) as session:
        scene = Scene(name=name, source="synthetic", state=state, path="/nowhere")
        session.add(scene)
        session.flush()
        return scene.id


def add_jobs(url, scene_id, n, method="leco") -> list[int]:
    with transaction(url) as session:
        return [
            submit(session, TRAIN, scene_id, TrainConfig(method=method, profile="smoke")).id
            for _ in range(n)
        ]


def add_job_before_0005(url, scene_id) -> int:
    """A training job written as a database before migration 0005 holds it (no kind, no parent): the
    models describe the newest schema, so the row goes in through the reflected tables."""
    from sqlalchemy import MetaData, insert

    cfg = TrainConfig(method="leco", profile="smoke")
    tables = MetaData()
    with engine_for(url).begin() as connection:
        tables.reflect(connection, only=["jobs", "job_phases"])
        jobs, phases = tables.tables["jobs"], tables.tables["job_phases"]
        job = connection.execute(
            insert(jobs)
            .values(
                scene_id=scene_id,
                state="queued",
                method="leco",
                profile="smoke",
                config=cfg.model_dump(mode="json"),
                step=0,
                total_steps=40,
                attempts=0,
                cancel_requested=False,
                submitted_at=utcnow().replace(tzinfo=None),
            )
            .returning(jobs.c.id)
        ).scalar_one()
        for position, phase in enumerate(cfg.phases):
            connection.execute(
                insert(phases).values(
                    job_id=job,
                    name=phase,
                    position=position,
                    state="queued",
                    steps_total=cfg.phase_steps(phase),
                    step=0,
                )
            )
    return job


def test_migrations_upgrade_an_empty_database_to_the_models(database_url):
    with pytest.raises(SchemaError, match="empty database.*leco db upgrade"):
        check_schema(database_url)
    assert upgrade(database_url) == (None, head_revision())
    check_schema(database_url)
    with engine_for(database_url).connect() as connection:
        assert (
            compare_metadata(
                MigrationContext.configure(connection, opts={"compare_type": True}), Base.metadata
            )
            == []
        )
        tables = set(inspect(connection).get_table_names())
    assert {
        "scenes",
        "jobs",
        "job_phases",
        "metrics",
        "artifacts",
        "idempotency_keys",
        "alembic_version",
    } <= tables
    # a second upgrade changes nothing
    assert upgrade(database_url) == (head_revision(), head_revision())


def add_artifact(url, job_id, name="summary.json") -> int:
    with transaction(url) as session:
        row = Artifact(
            job_id=job_id,
            kind="report",
            name=name,
            size=2,
            sha256="0" * 64,
            content_type="application/json",
        )
        session.add(row)
        session.flush()
        return row.id


def test_ids_of_deleted_scenes_jobs_and_artifacts_are_never_given_out_again(database_url):
    # Found by the stateful API fuzz: SQLite gave a new row the largest id + 1, so the job submitted
    # after the newest one was deleted took its id, and a client or an idempotent replay holding
    # that id was shown another job. Rows written before migration 0004 (which rebuilds SQLite's
    # tables) keep their ids.
    from alembic import command

    command.upgrade(alembic_config(database_url), "0003")
    scene = add_scene(database_url, "before")
    job = add_job_before_0005(database_url, scene)
    artifact = add_artifact(database_url, job)
    upgrade(database_url)
    with transaction(database_url) as session:
        assert (
            session.get(Scene, scene).name == "before" and session.get(Job, job).scene_id == scene
        )
        # 0005's default
        assert session.get(Job, job).kind == "train" and session.get(Job, job).parent_id is None
        assert session.get(Artifact, artifact).job_id == job
        assert len(session.scalars(select(JobPhase).where(JobPhase.job_id == job)).all()) == 2
        session.delete(session.get(Job, job))  # the newest of each, phases and artifact with it
        session.flush()
        session.delete(session.get(Scene, scene))
    scene_2 = add_scene(database_url, "after")
    [job_2] = add_jobs(database_url, scene_2, 1)
    artifact_2 = add_artifact(database_url, job_2)
    assert scene_2 > scene and job_2 > job and artifact_2 > artifact


def test_server_refuses_an_out_of_date_schema(database_url, tmp_path):
    from service.api.app import create_app
    from service.settings import Settings

    with pytest.raises(SchemaError, match="run `leco db upgrade`"):
        create_app(Settings(data_dir=tmp_path, database_url=database_url))
    upgrade(database_url)
    # pretend the code moved on to a newer revision
    with engine_for(database_url).begin() as connection:
        connection.exec_driver_sql("UPDATE alembic_version SET version_num = 'older'")
    assert current_revision(database_url) == "older"
    with pytest.raises(SchemaError, match="revision older, this code needs revision"):
        create_app(Settings(data_dir=tmp_path, database_url=database_url))


def test_sqlite_runs_in_wal_with_foreign_keys(tmp_path):
    url = f"sqlite:///{tmp_path / 'x.db'}"
    with engine_for(url).connect() as connection:
        assert connection.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
        assert connection.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
        assert connection.exec_driver_sql("PRAGMA busy_timeout").scalar() == 30000


def test_concurrent_claims_never_share_a_job(service_settings):
    url = service_settings.db_url
    scene = add_scene(url)
    jobs = add_jobs(url, scene, 24)
    claimed: dict[str, list] = {f"d{i}": [] for i in range(6)}
    start = threading.Barrier(6)

    def dispatcher(owner):
        start.wait()
        while (got := queue.claim(url, owner, 60)) is not None:
            claimed[owner].append(got)

    threads = [threading.Thread(target=dispatcher, args=(o,)) for o in claimed]
    [t.start() for t in threads]
    [t.join() for t in threads]
    ids = [job for got in claimed.values() for job, _ in got]
    assert sorted(ids) == jobs  # every job exactly once
    assert sum(1 for got in claimed.values() if got) >= 2  # they really competed
    with transaction(url) as session:
        rows = session.execute(select(Job.id, Job.state, Job.attempts, Job.lease_owner)).all()
    owners = {job: owner for owner, got in claimed.items() for job, _ in got}
    assert all(
        state == "running" and attempts == 1 and owner == owners[i]
        for i, state, attempts, owner in rows
    )


def test_claim_waits_for_a_ready_scene_and_takes_the_oldest(service_settings):
    url = service_settings.db_url
    generating, ready = add_scene(url, "g", "generating"), add_scene(url, "r")
    first = add_jobs(url, generating, 1)[0]
    second, third = add_jobs(url, ready, 2)
    assert queue.claim(url, "a", 60) == (second, 1)
    with transaction(url) as session:
        session.get(Scene, generating).state = "ready"
    assert queue.claim(url, "a", 60) == (first, 1)
    assert queue.claim(url, "a", 60) == (third, 1)
    assert queue.claim(url, "a", 60) is None


def test_lease_expiry_requeues_then_fails_with_the_last_error(service_settings):
    url = service_settings.db_url
    job = add_jobs(url, add_scene(url), 1)[0]

    def expire():
        with transaction(url) as session:
            session.execute(update(Job).values(lease_expires_at=utcnow() - timedelta(seconds=1)))

    for attempt in (1, 2):
        assert queue.claim(url, f"d{attempt}", 60) == (job, attempt)
        assert queue.heartbeat(url, job, attempt, f"d{attempt}", 60)
        assert queue.requeue_expired(url, max_attempts=3) == []  # lease still valid
        expire()
        assert queue.requeue_expired(url, max_attempts=3) == [(job, "queued")]
        assert not queue.heartbeat(url, job, attempt, f"d{attempt}", 60)  # the old owner lost it
        assert not queue.finish(url, job, attempt, "succeeded")  # and cannot finish it
    assert queue.claim(url, "d3", 60) == (job, 3)
    expire()
    assert queue.requeue_expired(url, max_attempts=3) == [(job, "failed")]
    with transaction(url) as session:
        row = session.get(Job, job)
        phases = session.scalars(select(JobPhase.state).where(JobPhase.job_id == job)).all()
    assert row.state == "failed" and row.attempts == 3
    assert "lease of attempt 3 expired" in row.error and "no attempts left (3 of 3)" in row.error
    assert set(phases) == {"failed"}


def test_release_hands_a_running_job_back_only_for_the_attempt_holding_it(service_settings):
    url = service_settings.db_url
    job, cancelled = add_jobs(url, add_scene(url), 2)
    assert queue.claim(url, "d1", 60) == (job, 1)
    queue.phase_started(url, job, 1, "occupancy")
    assert not queue.release(url, job, 2, "not mine")  # another attempt cannot
    assert queue.release(url, job, 1, "dispatcher d1 stopped")
    assert not queue.release(url, job, 1, "twice")  # it is queued now
    with transaction(url) as session:
        row = session.get(Job, job)
        phases = session.scalars(select(JobPhase.state).where(JobPhase.job_id == job)).all()
    assert (row.state, row.attempts, row.lease_owner, row.error) == (
        "queued",
        1,
        None,
        "dispatcher d1 stopped",
    )
    assert set(phases) == {"queued"}
    assert not queue.heartbeat(url, job, 1, "d1", 60) and not queue.finish(
        url, job, 1, "failed", "late error"
    )
    assert queue.claim(url, "d2", 60) == (job, 2)  # the next claim resumes it
    assert queue.claim(url, "d2", 60) == (cancelled, 1)
    queue.cancel(url, cancelled)
    # a cancel asked for is not undone by a restart
    assert not queue.release(url, cancelled, 1, "stopping")


def test_cancel_queued_at_once_running_by_request_and_not_after_the_end(service_settings):
    url = service_settings.db_url
    scene = add_scene(url)
    queued, running, done = add_jobs(url, scene, 3)
    assert queue.cancel(url, queued) == "cancelled"
    assert queue.claim(url, "d", 60) == (running, 1)
    assert queue.claim(url, "d", 60) == (done, 1)
    assert queue.finish(url, done, 1, "succeeded")
    assert queue.cancel(url, running) == "running"
    assert queue.cancel(url, done) == "succeeded"
    assert queue.cancel(url, 999) is None
    with transaction(url) as session:
        assert session.get(Job, running).cancel_requested
        assert session.get(Job, queued).finished_at is not None
        assert set(session.scalars(select(JobPhase.state).where(JobPhase.job_id == queued))) == {
            "cancelled"
        }
        assert set(session.scalars(select(JobPhase.state).where(JobPhase.job_id == done))) == {
            "succeeded"
        }
    assert queue.claim(url, "d", 60) is None  # the cancelled job is never claimed


def test_leco_serve_refuses_an_unmigrated_database_and_says_what_to_run(
    database_url, tmp_path, monkeypatch, capsys
):
    from cli.main import main

    monkeypatch.setenv("DATABASE_URL", database_url)
    monkeypatch.setenv("LECO_DATA_DIR", str(tmp_path / "data"))
    assert main(["serve", "--no-auth"]) == 2
    err = capsys.readouterr().err
    assert "leco: error:" in err and "empty database" in err and "run `leco db upgrade`" in err
    assert main(["db", "upgrade"]) == 0
    assert head_revision() in capsys.readouterr().out
    check_schema(database_url)


def test_scene_names_of_digits_alone_are_renamed_so_they_never_read_as_ids(database_url):
    from alembic import command

    command.upgrade(alembic_config(database_url), "0005")
    plain, digits, clash, taken = (
        add_scene(database_url, n) for n in ("city", "46", "7", "scene-7")
    )
    upgrade(database_url)
    with transaction(database_url) as session:
        names = {i: session.get(Scene, i).name for i in (plain, digits, clash, taken)}
    assert names == {plain: "city", digits: "scene-46", clash: f"scene-7-{clash}", taken: "scene-7"}

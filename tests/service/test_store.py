"""The artifact store on SQLite and PostgreSQL: content-addressed bytes, verified reads, no row
without its bytes and no bytes without a row, replacement, pruning and deletion."""

import hashlib
import os

import pytest
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError

from service.db import reading
from service.store import ArtifactError, ArtifactStore, CorruptArtifact
from service.tables import Artifact
from tests.service.test_db import add_jobs, add_scene


def blobs(root):
    return sorted(p.name for p in root.rglob("*") if p.is_file() and p.parent.name != "tmp")


@pytest.fixture
def store_and_job(service_settings):
    url = service_settings.db_url
    job = add_jobs(url, add_scene(url), 1)[0]
    return ArtifactStore(url, service_settings.artifacts), job


def test_put_verify_replace_and_delete(store_and_job, tmp_path):
    store, job = store_and_job
    data = b"checkpoint bytes" * 1000
    meta = store.put(job, "checkpoint", "a.pt", data, phase="main", step=10)
    sha = hashlib.sha256(data).hexdigest()
    assert (
        meta["sha256"] == sha
        and meta["size"] == len(data)
        and meta["content_type"] == "application/octet-stream"
    )
    assert store.verified_path(meta).read_bytes() == data
    assert store.blob_path(sha).relative_to(store.root).parts[:2] == (sha[:2], sha[2:4])
    # the same bytes under a second name share one blob; replacing a name frees its old blob
    twin = store.put(job, "report", "b.json", data)
    assert blobs(store.root) == [sha] and twin["content_type"] == "application/json"
    store.put(job, "checkpoint", "a.pt", b"newer", phase="main", step=20)
    assert len(blobs(store.root)) == 2
    store.put(job, "report", "b.json", b"{}")
    # no row references it any more
    assert hashlib.sha256(data).hexdigest() not in blobs(store.root)
    assert store.delete_job(job) == 2 and blobs(store.root) == []
    assert not list((store.root / "tmp").iterdir())


def test_corrupted_or_missing_bytes_are_detected(store_and_job):
    store, job = store_and_job
    meta = store.put(job, "render", "r.png", b"\x89PNG fake image")
    path = store.blob_path(meta["sha256"])
    os.chmod(path, 0o644)
    assert store.verified_path(meta) == path  # hashed once ...
    os.utime(path, ns=(1, 1))
    assert store.verified_path(meta) == path  # ... and again for a new version of the file
    path.write_bytes(b"\x89PNG fake imagE")  # one flipped byte, same size
    with pytest.raises(CorruptArtifact, match="do not match their sha256"):
        store.verified_path(meta)
    path.unlink()
    with pytest.raises(CorruptArtifact, match="bytes are missing"):
        store.verified_path(meta)


def test_a_failed_row_leaves_no_bytes(store_and_job):
    store, job = store_and_job
    with pytest.raises(IntegrityError):  # the foreign key refuses a job that does not exist
        store.put(job + 100, "report", "x.json", b"orphan?")
    assert blobs(store.root) == []
    with reading(store.db_url) as session:
        assert session.scalars(select(Artifact)).all() == []


def test_an_unwritable_root_fails_cleanly(service_settings, tmp_path):
    url = service_settings.db_url
    job = add_jobs(url, add_scene(url), 1)[0]
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the artifact root should be")
    with pytest.raises(ArtifactError, match="not writable"):
        ArtifactStore(url, blocker).put(job, "report", "x.json", b"{}")
    with reading(url) as session:
        assert session.scalars(select(Artifact)).all() == []
    with pytest.raises(ValueError, match="artifact kind 'model'"):
        ArtifactStore(url, tmp_path / "ok").put(job, "model", "x", b"")


def test_prune_keeps_the_newest_checkpoints(store_and_job):
    store, job = store_and_job
    for step in (10, 20, 30, 40):
        store.put(job, "checkpoint", f"c{step}.pt", f"state {step}".encode(), step=step)
    assert store.prune(job, "checkpoint", keep=2) == 2
    with reading(store.db_url) as session:
        assert sorted(session.scalars(select(Artifact.step))) == [30, 40]
    assert len(blobs(store.root)) == 2


def test_what_a_crash_leaves_behind_is_collected_and_nothing_else(store_and_job):
    """A staged file or a placed blob whose row never committed (a crash between the steps) is
    removed by `collect_orphans` (`leco db gc`, and at start-up); stored artifacts and fresh staging
    stay."""
    import os
    import time

    store, job = store_and_job
    kept = store.put(job, "render", "a.png", b"kept bytes")
    root = store.root
    orphan_sha = "ab" * 32
    orphan = store.blob_path(orphan_sha)
    orphan.parent.mkdir(parents=True, exist_ok=True)
    orphan.write_bytes(b"placed, never committed")
    (root / "tmp").mkdir(exist_ok=True)
    old, fresh = root / "tmp" / "incoming-old", root / "tmp" / "incoming-fresh"
    old.write_bytes(b"x" * 10)
    fresh.write_bytes(b"y")
    hour_ago = time.time() - 7200
    os.utime(old, (hour_ago, hour_ago))
    removed = store.collect_orphans(min_age_s=3600)
    assert removed == {"staged": 1, "blobs": 1, "bytes": 10 + len(b"placed, never committed")}
    assert not orphan.exists() and not old.exists() and fresh.exists()
    assert store.verified_path(kept).read_bytes() == b"kept bytes"
    assert store.collect_orphans(min_age_s=3600) == {"staged": 0, "blobs": 0, "bytes": 0}


def test_a_blob_is_hashed_once_per_version_not_per_download(store_and_job, monkeypatch):
    import service.store

    store, job = store_and_job
    meta = store.put(job, "checkpoint", "c.pt", b"x" * 100_000)
    hashed = []
    real = hashlib.sha256
    monkeypatch.setattr(service.store.hashlib, "sha256", lambda *a: hashed.append(1) or real(*a))
    for _ in range(5):
        store.verified_path(meta)  # five Range requests: one hash
    assert len(hashed) == 1
    os.utime(store.blob_path(meta["sha256"]), ns=(1, 1))  # a new version of the file: hashed again
    store.verified_path(meta)
    assert len(hashed) == 2

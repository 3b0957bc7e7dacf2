"""The database-backed artifact store: metadata rows in the database, bytes under the artifact root
in content-addressed files (root/ab/cd/<sha256>).

Write order: bytes to a temporary file, fsync, rename into place, then the row commits. A blob is
renamed into place and unlinked only inside a database transaction that holds a per-sha lock (BEGIN
IMMEDIATE on SQLite, an advisory lock on PostgreSQL), so "the last row went away" and "a new row
arrived" never cross: no row without its bytes, and no bytes left behind by a failed write. Reads
verify the sha256."""

from __future__ import annotations

import hashlib
import io
import mimetypes
import os
import tempfile
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy import delete, func, select, text
from sqlalchemy.orm import Session

from service import queue
from service.db import reading, transaction
from service.tables import ARTIFACT_KINDS, Artifact, utcnow
from workers.store import StoreWriteError

CHUNK = 1 << 20
CONTENT_TYPES = {
    ".png": "image/png",
    ".json": "application/json",
    ".jsonl": "application/x-ndjson",
    ".pt": "application/octet-stream",
    ".ply": "application/x-ply",
    ".mp4": "video/mp4",
}


class ArtifactError(StoreWriteError):
    """An artifact that cannot be written or read back, with the reason."""


class CorruptArtifact(ArtifactError):
    pass


def content_type_for(name: str) -> str:
    suffix = Path(name).suffix.lower()
    return CONTENT_TYPES.get(suffix) or mimetypes.guess_type(name)[0] or "application/octet-stream"


@dataclass(frozen=True)
class ArtifactStore:
    db_url: str
    root: Path

    def blob_path(self, sha256: str) -> Path:
        return Path(self.root) / sha256[:2] / sha256[2:4] / sha256

    # ----- writing
    # -----------------------------------------------------------------------------------
    def put(
        self,
        job_id: int,
        kind: str,
        name: str,
        source: Path | bytes,
        *,
        phase: str | None = None,
        step: int | None = None,
        content_type: str | None = None,
        attempt: int | None = None,
    ) -> dict:
        """Stores `source` as the job's (kind, name), replacing an earlier artifact of that name;
        returns its metadata. Raises ArtifactError (nothing stored) when the bytes cannot be
        written. With `attempt` (a run's write), only while that attempt holds the job (queue.hold;
        else StaleAttempt and nothing stored)."""
        if kind not in ARTIFACT_KINDS:
            raise ValueError(f"artifact kind {kind!r}: expected one of {', '.join(ARTIFACT_KINDS)}")
        staged: Path | None  # None once placed: then a failure has no staged file to remove
        staged, sha, size = self._stage(source)
        replaced: str | None = None
        try:
            with transaction(self.db_url) as session:
                if attempt is not None:
                    queue.hold(session, job_id, attempt)
                self._lock(session, sha)
                self._place(staged, sha)
                staged = None
                row = session.scalars(
                    select(Artifact).where(
                        Artifact.job_id == job_id, Artifact.kind == kind, Artifact.name == name
                    )
                ).first()
                if row is None:
                    row = Artifact(job_id=job_id, kind=kind, name=name)
                    session.add(row)
                elif row.sha256 != sha:
                    replaced = row.sha256
                row.phase, row.step, row.size, row.sha256 = phase, step, size, sha
                row.content_type = content_type or content_type_for(name)
                row.created_at, row.attempt = utcnow(), attempt
                session.flush()
                meta = describe(row)
        except BaseException:
            if staged is not None:
                staged.unlink(missing_ok=True)
            self._collect(sha)  # the blob may now be unreferenced: the row never committed
            raise
        if replaced:
            self._collect(replaced)
        return meta

    def _stage(self, source: Path | bytes) -> tuple[Path, str, int]:
        tmp_dir = Path(self.root) / "tmp"
        try:
            tmp_dir.mkdir(parents=True, exist_ok=True)
            fd, tmp_name = tempfile.mkstemp(dir=tmp_dir, prefix="incoming-")
        except OSError as error:
            raise ArtifactError(
                f"artifact root {self.root} is not writable: {error.strerror or error}"
            ) from error
        tmp, digest, size = Path(tmp_name), hashlib.sha256(), 0
        try:
            with os.fdopen(fd, "wb") as out:
                with (
                    open(source, "rb") if isinstance(source, (str, Path)) else io.BytesIO(source)
                ) as reader:
                    while chunk := reader.read(CHUNK):
                        digest.update(chunk)
                        out.write(chunk)
                        size += len(chunk)
                out.flush()
                os.fsync(out.fileno())
        except OSError as error:
            tmp.unlink(missing_ok=True)
            raise ArtifactError(
                f"writing an artifact under {self.root} failed: {error.strerror or error}"
            ) from error
        return tmp, digest.hexdigest(), size

    def _place(self, staged: Path, sha: str) -> None:
        target = self.blob_path(sha)
        try:
            _make_dirs_durably(target.parent, Path(self.root))
            os.replace(staged, target)  # same bytes if it already existed: the rename is harmless
            _fsync_dir(target.parent)
        except OSError as error:
            raise ArtifactError(
                f"storing an artifact under {self.root} failed: {error.strerror or error}"
            ) from error

    def _lock(self, session: Session, sha: str) -> None:
        if session.get_bind().dialect.name == "postgresql":
            session.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": int(sha[:15], 16)})
        # SQLite: the write transaction (BEGIN IMMEDIATE) already excludes every other writer.

    def _collect(self, sha: str) -> None:
        """Unlinks the blob when no row references it any more."""
        try:
            with transaction(self.db_url) as session:
                self._lock(session, sha)
                if not session.scalar(
                    select(func.count()).select_from(Artifact).where(Artifact.sha256 == sha)
                ):
                    self.blob_path(sha).unlink(missing_ok=True)
        except OSError:
            pass  # best effort: an unreadable root fails the write itself, loudly, elsewhere

    def collect_orphans(self, min_age_s: float = 3600.0) -> dict:
        """Removes what a crash can leave behind: staged files older than `min_age_s` (a live write
        stages for seconds) and blobs no row references (checked under the blob's lock, as `put`
        places and commits under it, so a write in flight is never collected). Returns what it
        removed."""
        import time

        removed = {"staged": 0, "blobs": 0, "bytes": 0}
        root, cutoff = Path(self.root), time.time() - min_age_s
        for staged in (root / "tmp").glob("incoming-*") if (root / "tmp").is_dir() else []:
            _unlink_counted(staged, removed, "staged", older_than=cutoff)
        # one read for all; only unreferenced ones are re-checked
        with reading(self.db_url) as session:
            referenced = set(session.scalars(select(Artifact.sha256).distinct()))
        for blob in root.glob("[0-9a-f][0-9a-f]/[0-9a-f][0-9a-f]/*"):
            sha = blob.name
            if len(sha) != 64 or blob.parent.parent.name != sha[:2] or blob.parent.name != sha[2:4]:
                continue
            if sha in referenced:
                continue
            with transaction(self.db_url) as session:
                self._lock(session, sha)
                if not session.scalar(
                    select(func.count()).select_from(Artifact).where(Artifact.sha256 == sha)
                ):
                    _unlink_counted(blob, removed, "blobs")
        return removed

    # ----- reading and deleting
    # ----------------------------------------------------------------------
    def verified_path(self, meta: dict) -> Path:
        """The blob's path after checking its size and sha256 against the row. The hash is computed
        once per file version and process (a 1-byte Range request re-hashed a whole checkpoint every
        time); a blob rewritten in place has a new inode or mtime and is hashed again."""
        path = self.blob_path(meta["sha256"])
        what = f"artifact {meta['id']} ({meta['name']})"
        try:
            stat = path.stat()
        except FileNotFoundError:
            raise CorruptArtifact(f"{what}: its bytes are missing from the artifact root") from None
        identity = (meta["sha256"], stat.st_dev, stat.st_ino, stat.st_mtime_ns, stat.st_size)
        if stat.st_size == meta["size"] and _VERIFIED.seen(identity):
            return path
        digest = hashlib.sha256()
        with path.open("rb") as f:
            while chunk := f.read(CHUNK):
                digest.update(chunk)
        if digest.hexdigest() != meta["sha256"] or stat.st_size != meta["size"]:
            raise CorruptArtifact(
                f"{what}: stored bytes do not match their sha256 {meta['sha256']} (found "
                f"{digest.hexdigest()}): the file was corrupted after it was written"
            )
        _VERIFIED.add(identity)
        return path

    def delete(self, artifact_ids: list[int]) -> int:
        with transaction(self.db_url) as session:
            shas = list(
                session.scalars(select(Artifact.sha256).where(Artifact.id.in_(artifact_ids)))
            )
            session.execute(delete(Artifact).where(Artifact.id.in_(artifact_ids)))
        for sha in set(shas):
            self._collect(sha)
        return len(shas)

    def shas_of(self, session: Session, job_ids: list[int]) -> set[str]:
        """The blobs the jobs' artifacts point at, read in the caller's transaction (before it
        deletes the jobs, whose artifact rows go with them by ON DELETE CASCADE)."""
        return set(session.scalars(select(Artifact.sha256).where(Artifact.job_id.in_(job_ids))))

    def collect(self, shas: set[str]) -> None:
        """Unlinks each blob no row references any more (after the rows that did were deleted)."""
        for sha in shas:
            self._collect(sha)

    def delete_job(self, job_id: int) -> int:
        with transaction(self.db_url) as session:
            ids = list(session.scalars(select(Artifact.id).where(Artifact.job_id == job_id)))
        return self.delete(ids) if ids else 0

    def prune(self, job_id: int, kind: str, keep: int, attempt: int | None = None) -> int:
        """Keeps the `keep` newest artifacts of a kind (by step) for a job, deletes the rest (with
        `attempt`: only while that attempt holds the job)."""
        with transaction(self.db_url) as session:
            if attempt is not None:
                queue.hold(session, job_id, attempt)
            ids = list(
                session.scalars(
                    select(Artifact.id)
                    .where(Artifact.job_id == job_id, Artifact.kind == kind)
                    .order_by(Artifact.step.desc(), Artifact.id.desc())
                    .offset(keep)
                )
            )
        return self.delete(ids) if ids else 0


class _Seen:
    """A bounded set (least recently used out) of blob versions already hashed by this process."""

    def __init__(self, size: int = 65_536):
        self.size, self.lock = size, threading.Lock()
        self.items: OrderedDict[tuple, None] = OrderedDict()

    def seen(self, key: tuple) -> bool:
        with self.lock:
            if key in self.items:
                self.items.move_to_end(key)
                return True
            return False

    def add(self, key: tuple) -> None:
        with self.lock:
            self.items[key] = None
            while len(self.items) > self.size:
                self.items.popitem(last=False)


_VERIFIED = _Seen()


def describe(row: Artifact) -> dict:
    return {
        "id": row.id,
        "job_id": row.job_id,
        "phase": row.phase,
        "kind": row.kind,
        "step": row.step,
        "name": row.name,
        "size": row.size,
        "sha256": row.sha256,
        "content_type": row.content_type,
        "created_at": row.created_at,
    }


def _unlink_counted(path: Path, removed: dict, kind: str, older_than: float | None = None) -> None:
    try:
        stat = path.stat()
        if older_than is None or stat.st_mtime < older_than:
            path.unlink()
            removed[kind] += 1
            removed["bytes"] += stat.st_size
    except FileNotFoundError:  # another collector got there first
        pass


def _make_dirs_durably(folder: Path, root: Path) -> None:
    """mkdir -p, then fsync the parent of every folder it created, so a crash cannot lose a blob's
    folder."""
    missing = []
    while not folder.exists() and folder != root and folder != folder.parent:
        missing.append(folder)
        folder = folder.parent
    for created in reversed(missing):
        created.mkdir(exist_ok=True)
        _fsync_dir(created.parent)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)

"""The service's database schema (SQLAlchemy 2). Alembic migrations in migrations/ create exactly
this; a test compares the migrated database with these models."""

from __future__ import annotations

from datetime import datetime, timezone

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    CheckConstraint,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
)
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

JOB_STATES = ("queued", "running", "succeeded", "failed", "cancelled")
TERMINAL = ("succeeded", "failed", "cancelled")
SCENE_STATES = ("generating", "posing", "ready", "failed")
ARTIFACT_KINDS = ("checkpoint", "render", "occupancy_model", "pointcloud", "report")


def utcnow() -> datetime:
    return datetime.now(timezone.utc)


class UTCDateTime(TypeDecorator):
    """Stored as naive UTC (SQLite has no time zones), always handed back aware."""

    impl = DateTime
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is not None and value.tzinfo is not None:
            value = value.astimezone(timezone.utc).replace(tzinfo=None)
        return value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        return value.replace(tzinfo=timezone.utc) if value is not None else None


# SQLite gives a new row the largest id + 1 unless the table is AUTOINCREMENT: deleting the newest
# job would hand its id to the next one, and whoever still held the old id (a client, a dashboard,
# an idempotent replay) would be shown another job. PostgreSQL's sequences never reuse an id.
NEVER_REUSED = {"sqlite_autoincrement": True}


def one_of(column: str, values: tuple[str, ...]) -> CheckConstraint:
    return CheckConstraint(
        f"{column} IN ({', '.join(repr(v) for v in values)})", name=f"{column}_valid"
    )


class Base(DeclarativeBase):
    pass


class Scene(Base):
    __tablename__ = "scenes"
    __table_args__ = (one_of("state", SCENE_STATES), NEVER_REUSED)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(128), unique=True)
    source: Mapped[str] = mapped_column(String(16))  # synthetic | upload | photos
    state: Mapped[str] = mapped_column(String(16))
    format: Mapped[str | None] = mapped_column(String(32))
    path: Mapped[str] = mapped_column(Text)
    generator: Mapped[dict | None] = mapped_column(JSON)  # {preset, seed} for synthetic scenes
    info: Mapped[dict | None] = mapped_column(JSON)  # `leco scene info --json` of the stored scene
    error: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class Job(Base):
    __tablename__ = "jobs"
    __table_args__ = (
        one_of("state", JOB_STATES),
        Index("ix_jobs_state_id", "state", "id"),
        NEVER_REUSED,
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    # An entry of the job-kind registry (service/jobs/kinds.py), which the API checks before
    # writing.
    kind: Mapped[str] = mapped_column(String(16), default="train", server_default="train")
    # The finished training job a render or export works on; deleting it deletes them (the API
    # refuses while one has not ended).
    parent_id: Mapped[int | None] = mapped_column(
        ForeignKey("jobs.id", ondelete="CASCADE"), index=True
    )
    scene_id: Mapped[int] = mapped_column(ForeignKey("scenes.id", ondelete="RESTRICT"), index=True)
    state: Mapped[str] = mapped_column(String(16), default="queued")
    method: Mapped[str] = mapped_column(String(16))
    profile: Mapped[str] = mapped_column(String(32))
    # TrainConfig, RenderConfig or ExportConfig (by kind), as submitted
    config: Mapped[dict] = mapped_column(JSON)
    phase: Mapped[str | None] = mapped_column(String(16))  # current phase
    step: Mapped[int] = mapped_column(Integer, default=0)  # global step of the latest metrics
    total_steps: Mapped[int] = mapped_column(Integer)
    rays_per_s: Mapped[float | None] = mapped_column(Float)  # latest throughput, for the ETA
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    lease_owner: Mapped[str | None] = mapped_column(String(128))
    lease_expires_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    error: Mapped[str | None] = mapped_column(Text)
    submitted_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime)


class JobPhase(Base):
    __tablename__ = "job_phases"
    __table_args__ = (UniqueConstraint("job_id", "name"), one_of("state", JOB_STATES))

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    job_id: Mapped[int] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"))
    name: Mapped[str] = mapped_column(String(16))
    position: Mapped[int] = mapped_column(Integer)
    state: Mapped[str] = mapped_column(String(16), default="queued")
    steps_total: Mapped[int] = mapped_column(Integer)
    step: Mapped[int] = mapped_column(Integer, default=0)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime)


class Metric(Base):
    """One value per (job, phase, name, step): a replayed step overwrites, never duplicates."""

    __tablename__ = "metrics"
    # Polling reads "steps after N" and "the latest step of each phase"; both would scan the job's
    # rows without these.
    __table_args__ = (
        Index("ix_metrics_job_step", "job_id", "step"),
        Index("ix_metrics_job_phase_step", "job_id", "phase", "step"),
    )

    job_id: Mapped[int] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True)
    phase: Mapped[str] = mapped_column(String(16), primary_key=True)
    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    step: Mapped[int] = mapped_column(Integer, primary_key=True)
    value: Mapped[float] = mapped_column(Float)
    # training time of the run at this step
    wall_time_s: Mapped[float | None] = mapped_column(Float)
    # the attempt that wrote it (the fencing token)
    attempt: Mapped[int | None] = mapped_column(Integer)


class Artifact(Base):
    """Metadata only: the bytes live under the artifact root, named by their sha256."""

    __tablename__ = "artifacts"
    __table_args__ = (
        UniqueConstraint("job_id", "kind", "name"),
        one_of("kind", ARTIFACT_KINDS),
        NEVER_REUSED,
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    job_id: Mapped[int] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    phase: Mapped[str | None] = mapped_column(String(16))
    kind: Mapped[str] = mapped_column(String(32))
    step: Mapped[int | None] = mapped_column(Integer)
    name: Mapped[str] = mapped_column(String(255))
    size: Mapped[int] = mapped_column(BigInteger)
    sha256: Mapped[str] = mapped_column(String(64), index=True)
    content_type: Mapped[str] = mapped_column(String(128))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    # the attempt that wrote it (the fencing token)
    attempt: Mapped[int | None] = mapped_column(Integer)


class IdempotencyKey(Base):
    __tablename__ = "idempotency_keys"

    key: Mapped[str] = mapped_column(String(255), primary_key=True)
    request_hash: Mapped[str] = mapped_column(String(64))
    state: Mapped[str] = mapped_column(String(16))  # in_flight | done
    status_code: Mapped[int | None] = mapped_column(Integer)
    response: Mapped[dict | None] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)

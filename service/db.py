"""Engines, sessions and the schema version. SQLite (the embedded default) runs in WAL mode with a
busy timeout and foreign keys on, so the API, the dispatcher and the training processes can share
one file; PostgreSQL is selected by DATABASE_URL. Migrations are applied only by `leco db upgrade`
(or by `leco serve` on the embedded default, for the user), never implicitly by the API."""

from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator, TypeVar

from sqlalchemy import Connection, Engine, create_engine, event
from sqlalchemy.exc import InterfaceError, OperationalError
from sqlalchemy.orm import Session, sessionmaker

from model.errors import Failed, Unavailable
from workers.store import StoreWriteError

if TYPE_CHECKING:
    import sqlite3

    from alembic.config import Config
    from sqlalchemy.pool import ConnectionPoolEntry

log = logging.getLogger("leco.db")
T = TypeVar("T")
# Errors of the connection, not of the statement: the server restarting or refusing connections, a
# dropped connection, SQLite's lock timeout. Worth retrying; a constraint or syntax error is not.
UNAVAILABLE = (OperationalError, InterfaceError)

MIGRATIONS = Path(__file__).resolve().parents[1] / "migrations"


class SchemaError(Failed):
    """The database is not at the schema this code needs; the message says what to run."""


def normalise_url(url: str) -> str:
    # psycopg 3 is the driver we install; plain postgresql:// would ask SQLAlchemy for psycopg2.
    if url.startswith("postgresql://") or url.startswith("postgres://"):
        return "postgresql+psycopg://" + url.split("://", 1)[1]
    return url


@lru_cache(maxsize=None)
def engine_for(url: str) -> Engine:
    url = normalise_url(url)
    if url.startswith("sqlite"):
        path = url.split("///", 1)[-1]
        if path and path != ":memory:":
            Path(path).parent.mkdir(parents=True, exist_ok=True)
        engine = create_engine(url, connect_args={"timeout": 30, "check_same_thread": False})
        event.listen(engine, "connect", _sqlite_pragmas)
        event.listen(engine, "begin", _sqlite_begin)
        return engine
    return create_engine(url, pool_pre_ping=True, pool_size=10, max_overflow=20)


def _sqlite_begin(conn: Connection) -> None:
    # Writers take the lock up front (BEGIN IMMEDIATE waits out busy_timeout); a deferred
    # transaction that reads and then writes can fail at once with "database is locked" when another
    # writer got in between.
    conn.exec_driver_sql(
        "BEGIN IMMEDIATE" if conn.get_execution_options().get("writes", True) else "BEGIN"
    )


def _sqlite_pragmas(dbapi_connection: sqlite3.Connection, _record: ConnectionPoolEntry) -> None:
    # autocommit at the driver; SQLAlchemy's "begin" event opens transactions
    dbapi_connection.isolation_level = None
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA busy_timeout=30000")
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.close()


@lru_cache(maxsize=None)
def session_factory(url: str, writes: bool = True) -> sessionmaker[Session]:
    return sessionmaker(engine_for(url).execution_options(writes=writes), expire_on_commit=False)


@contextmanager
def transaction(url: str) -> Iterator[Session]:
    """One unit of work that may write: committed on success, rolled back on any error."""
    with session_factory(url)() as session, session.begin():
        yield session


@contextmanager
def reading(url: str) -> Iterator[Session]:
    """A read-only snapshot (on SQLite it does not wait for writers)."""
    with session_factory(url, writes=False)() as session, session.begin():
        yield session


class DatabaseUnavailable(Unavailable, StoreWriteError):
    """The database did not answer within the retry budget."""

    retryable = True


def retrying(what: str, call: Callable[[], T], budget_s: float) -> T:
    """Runs `call` (one whole transaction), again after a pause while the database is unavailable,
    for up to `budget_s` seconds (Settings.retry_s: LECO_DB_RETRY_S). The dispatcher and training
    use it so that a database restart pauses them instead of failing jobs; the API does not (it
    answers 503 at once)."""
    deadline, pause = time.monotonic() + budget_s, 0.2
    while True:
        try:
            return call()
        except UNAVAILABLE as error:
            if time.monotonic() + pause > deadline:
                raise DatabaseUnavailable(
                    f"the database was unavailable for {budget_s:.0f} s while {what}: "
                    f"{first_line(error)}"
                ) from error
            log.warning(
                "database unavailable while %s (retrying in %.1f s): %s",
                what,
                pause,
                first_line(error),
            )
            time.sleep(pause)
            pause = min(pause * 2, 5.0)


def first_line(error: BaseException) -> str:
    text = str(getattr(error, "orig", None) or error).strip()
    return text.splitlines()[0] if text else type(error).__name__


def alembic_config(url: str) -> Config:
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    config.set_main_option("sqlalchemy.url", normalise_url(url).replace("%", "%%"))
    return config


def upgrade(url: str) -> tuple[str | None, str]:
    """Applies every migration; returns (revision before, revision after)."""
    from alembic import command

    before = current_revision(url)
    command.upgrade(alembic_config(url), "head")
    return before, head_revision()


def head_revision() -> str:
    from alembic.script import ScriptDirectory

    head = ScriptDirectory.from_config(alembic_config("sqlite://")).get_current_head()
    if head is None:  # alembic's answer for a migrations folder without any revision
        raise SchemaError(f"no migrations found in {MIGRATIONS}")
    return head


def current_revision(url: str) -> str | None:
    from alembic.runtime.migration import MigrationContext

    with engine_for(url).connect() as connection:
        return MigrationContext.configure(connection).get_current_revision()


def check_schema(url: str) -> None:
    """Raises SchemaError unless the database is at the newest migration."""
    head, current = head_revision(), current_revision(url)
    if current != head:
        where = "an empty database" if current is None else f"revision {current}"
        raise SchemaError(
            f"the database ({redact(url)}) is at {where}, this code needs revision {head}: run "
            "`leco db upgrade` (with the same DATABASE_URL) first"
        )


def redact(url: str) -> str:
    """The URL without its password, for messages and logs."""
    from sqlalchemy.engine import make_url

    return make_url(normalise_url(url)).render_as_string(hide_password=True)

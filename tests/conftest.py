"""Shared fixtures: the real scenes in ../shared/datasets (tests skip, saying why, when it is
absent), and the service's databases (SQLite, and the machine's PostgreSQL)."""

import itertools
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "datasets"


def shared_dataset(name: str) -> Path:
    path = SHARED / name
    if not path.is_dir():
        pytest.skip(
            f"shared dataset {name} not found at {path} (it ships beside the checkout in ../shared)"
        )
    return path


@pytest.fixture(scope="session", autouse=True)
def pixel_cache(tmp_path_factory) -> Path:
    """Training pixel caches (model/scenes/pixel_cache.py) go to a folder of this session, never to
    the user's ~/.cache; services and Ray workers the tests start inherit it."""
    import os

    cache = tmp_path_factory.mktemp("pixel-cache")
    os.environ["LECO_PIXEL_CACHE"] = str(cache)
    return cache


@pytest.fixture(scope="session")
def lego_dir() -> Path:
    return shared_dataset("nerf_synthetic_lego_200")


@pytest.fixture(scope="session")
def fern_dir() -> Path:
    return shared_dataset("nerf_llff_fern")


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """The tiny synthetic city (seed 0), generated once per session: exact depth maps and
    occupancy."""
    from model.scenes import load_scene
    from model.scenes.synthetic import generate

    out = tmp_path_factory.mktemp("tiny-scene") / "tiny-0"
    generate("tiny", 0, out)
    return load_scene(out)


@pytest.fixture(scope="session")
def city_scene(tmp_path_factory) -> tuple[Path, dict, float]:
    """The default synthetic city (seed 0) as `leco scene synth --preset city` makes it, generated
    once per session (tens of seconds): its folder, the generator's summary and the seconds it
    took."""
    from model.scenes.synthetic import generate

    out = tmp_path_factory.mktemp("city-scene") / "city-0"
    started = time.perf_counter()
    summary = generate("city", 0, out)
    return out, summary, time.perf_counter() - started


def free_port() -> int:
    """A free TCP port on the loopback interface, for a server a test starts."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ----- the service: every database test runs on SQLite and on the machine's real PostgreSQL
# ----------------
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


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request, tmp_path):
    """An empty database of each kind (no schema yet)."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'leco.db'}"
        return
    url = fresh_postgres_database()
    yield url
    drop_postgres_database(url)


@pytest.fixture
def service_settings(database_url, tmp_path):
    """Service settings on a migrated database of each kind, with a private data folder and artifact
    root."""
    from service.db import upgrade
    from service.settings import Settings

    upgrade(database_url)
    return Settings(
        data_dir=tmp_path / "data", database_url=database_url, local_cpus=2, lease_s=5.0
    )


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

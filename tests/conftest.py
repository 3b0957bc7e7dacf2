"""Shared fixtures: the real scenes in ../shared/datasets (tests skip, saying why, when it is
absent), and the service's databases (SQLite, and the machine's PostgreSQL)."""

import time
from pathlib import Path
from typing import Callable, Iterator

import pytest

from tests.helpers import PG_ADMIN, drop_postgres_database, fresh_postgres_database

pytest_plugins = ["tests.crash_report", "tests.parallel"]

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


@pytest.fixture(scope="module")
def local_ray():
    """A local Ray with two CPUs for the tests of one module (`pytest.mark.usefixtures`), shut
    down after them."""
    from workers.train.run import ensure_ray

    ensure_ray(2)
    yield
    import ray

    ray.shutdown()


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


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request, tmp_path):
    """An empty database of each kind (no schema yet)."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'leco.db'}"
        return
    url = fresh_postgres_database()
    yield url
    drop_postgres_database(url)


@pytest.fixture(scope="session")
def migrated(tmp_path_factory) -> Iterator[Callable[[str], None]]:
    """Brings an empty database of either kind to the head revision by copying one migrated once a
    session (a file for SQLite, a template database for PostgreSQL): running the migrations for
    each of the service's few hundred tests cost a third of a second each."""
    import sqlite3

    import psycopg

    from service.db import engine_for, upgrade

    templates: dict[str, str] = {}

    def template(kind: str) -> str:
        if kind not in templates:
            if kind == "sqlite":
                url = f"sqlite:///{tmp_path_factory.mktemp('template') / 'leco.db'}"
            else:
                url = fresh_postgres_database()
            upgrade(url)
            engine_for(url).dispose()  # a template database takes no connections while copied
            templates[kind] = url
        return templates[kind]

    def migrate(url: str) -> None:
        if url.startswith("sqlite"):
            # the backup API copies what the write-ahead log holds as well
            with sqlite3.connect(template("sqlite").split("///", 1)[1]) as source:
                with sqlite3.connect(url.split("///", 1)[1]) as target:
                    source.backup(target)
            return
        name, source = url.rsplit("/", 1)[1], template("postgresql").rsplit("/", 1)[1]
        with psycopg.connect(PG_ADMIN, autocommit=True) as conn:
            conn.execute(f"DROP DATABASE IF EXISTS {name} WITH (FORCE)")
            conn.execute(f"CREATE DATABASE {name} TEMPLATE {source}")

    yield migrate
    if "postgresql" in templates:
        drop_postgres_database(templates["postgresql"])


@pytest.fixture
def service_settings(database_url, tmp_path, migrated):
    """Service settings on a migrated database of each kind, with a private data folder and artifact
    root."""
    from service.db import check_schema
    from service.settings import Settings

    migrated(database_url)
    check_schema(database_url)  # at the head revision, as `leco serve` would find it
    return Settings(
        data_dir=tmp_path / "data", database_url=database_url, local_cpus=2, lease_s=5.0
    )


@pytest.fixture(scope="session")
def flight(tmp_path_factory) -> Path:
    """A small synthetic drone flight as photos (bench/photo_flight.py): 30 JPEGs of 320x240 with
    EXIF focal length and GPS, and truth.json with the exact cameras. Written once a session."""
    from bench.photo_flight import write_flight

    root = tmp_path_factory.mktemp("flight")
    write_flight(root, preset="city", seed=2, views=30, size=(320, 240))
    return root

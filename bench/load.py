"""`leco loadtest`: many dashboard-like pollers against a service that is training a job, on
loopback.

It starts `leco serve` (API + dispatcher + local Ray) on the given database, registers the tiny
synthetic city, submits a LeCO job and, once the job reports metrics, runs N concurrent pollers for
a bounded time. Each poller does what the dashboard's job view does: GET /v1/jobs/{id}, then GET its
metrics after the last step it has seen, then sleeps `interval` seconds. Every request's latency and
every error are recorded; the job is cancelled and the service stopped at the end. Reported:
p50/p95/p99/max per route, errors, requests/s, and how many training steps the job made meanwhile
(the pollers must not stall training)."""

from __future__ import annotations

import asyncio
import gc
import json
import os
import re
import secrets
import signal
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from bench.attacks import attack_bodies as build_attack_bodies
from bench.attacks import attack_tasks, scene_archive, verdict
from bench.slow_clients import fit_open_files, slow_client_tasks

ROOT = Path(__file__).resolve().parents[1]
STEP = re.compile(rb'"step":(\d+)')


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Service:
    """`leco serve` in a subprocess of its own process group, on `database_url` (None: embedded
    SQLite)."""

    def __init__(self, data_dir: Path, database_url: str | None, cpus: int = 2):
        self.data_dir, self.port, self.token = data_dir, free_port(), secrets.token_urlsafe(16)
        self.env = {
            **os.environ,
            "LECO_DATA_DIR": str(data_dir),
            "LECO_API_TOKENS": self.token,
            "LECO_LOCAL_CPUS": str(cpus),
        }
        for key in ("DATABASE_URL", "RAY_ADDRESS", "LECO_RAY_JOBS_ADDRESS"):
            self.env.pop(key, None)
        if database_url:
            self.env["DATABASE_URL"] = database_url

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def __enter__(self) -> "Service":
        self.data_dir.mkdir(parents=True, exist_ok=True)
        if "DATABASE_URL" in self.env:
            subprocess.run(
                [sys.executable, "-m", "cli", "db", "upgrade"],
                env=self.env,
                cwd=ROOT,
                check=True,
                capture_output=True,
            )
        self.log = open(self.data_dir / "serve.log", "w")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "cli", "serve", "--port", str(self.port)],
            env=self.env,
            cwd=ROOT,
            stdout=self.log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                if httpx.get(f"{self.url}/readyz", timeout=2).status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            if self.process.poll() is not None:
                raise RuntimeError(
                    "leco serve exited: " + (self.data_dir / "serve.log").read_text()[-2000:]
                )
            time.sleep(0.5)
        raise RuntimeError("leco serve did not become ready in 120 s")

    def __exit__(self, *exc) -> None:
        os.killpg(self.process.pid, signal.SIGTERM)
        try:
            self.process.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(self.process.pid, signal.SIGKILL)
        self.log.close()

    def client(self) -> httpx.Client:
        return httpx.Client(
            base_url=self.url, headers={"Authorization": f"Bearer {self.token}"}, timeout=60
        )


def start_job(api: httpx.Client, profile: str, overrides: dict | None = None) -> int:
    scene = api.post("/v1/scenes/synthetic", json={"preset": "tiny", "seed": 0}).json()
    while scene["state"] == "generating":
        time.sleep(0.3)
        scene = api.get(f"/v1/scenes/{scene['id']}").json()
    job = api.post(
        "/v1/jobs",
        json={
            "scene": scene["id"],
            "method": "leco",
            "profile": profile,
            "overrides": overrides or {},
            "metrics_every": 5,
        },
    ).json()
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        state = api.get(f"/v1/jobs/{job['id']}").json()
        if state["state"] == "running" and state["step"] > 0:
            return job["id"]
        if state["state"] in ("failed", "succeeded", "cancelled"):
            raise RuntimeError(f"the load test's job ended before the test began: {state}")
        time.sleep(0.5)
    raise RuntimeError("the load test's job did not start training in 300 s")


class Connection:
    """One keep-alive HTTP/1.1 connection that sends GETs and reads Content-Length answers (all this
    API sends on these routes). Hand-rolled on asyncio streams because a general client costs a
    millisecond or more of CPU per request, which on a 2-core machine would be taken from the server
    being measured."""

    def __init__(self, host: str, port: int, token: str):
        self.host, self.port = host, port
        self.headers = f"Host: {host}:{port}\r\nAuthorization: Bearer {token}\r\n\r\n".encode()
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def get(self, target: str) -> tuple[int, bytes]:
        if self.reader is None or self.writer is None:
            self.reader, self.writer = await asyncio.open_connection(self.host, self.port)
        reader, writer = self.reader, self.writer
        try:
            writer.write(b"GET " + target.encode() + b" HTTP/1.1\r\n" + self.headers)
            head = (await reader.readuntil(b"\r\n\r\n")).decode("latin-1").split("\r\n")
            fields = dict(line.lower().split(": ", 1) for line in head[1:] if ": " in line)
            if "content-length" not in fields:
                raise ValueError(f"an answer without Content-Length: {head[0]}")
            body = await reader.readexactly(int(fields["content-length"]))
            if fields.get("connection") == "close":
                self.close()
            return int(head[0].split(" ")[1]), body
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        self.reader = self.writer = None


async def poller(
    url: str, token: str, job: int, start: float, until: float, interval: float, samples: dict
) -> None:
    """Polls at a fixed rate (start, start + interval, ...) whatever each answer took, so a slow
    moment does not bunch the pollers into lockstep (and a slow server is not hidden by a slower
    client: no coordinated omission)."""
    host, port = url.split("//", 1)[1].rsplit(":", 1)
    connection, after, due = Connection(host, int(port), token), 0, start
    while due < until:
        await asyncio.sleep(max(0.0, due - time.monotonic()))
        for route in ("job", "metrics"):
            target = (
                f"/v1/jobs/{job}"
                if route == "job"
                else f"/v1/jobs/{job}/metrics?after_step={after}&max_points=500"
            )
            started, body = time.perf_counter(), b""
            try:
                status, body = await asyncio.wait_for(connection.get(target), 30)
                ok = status == 200
            except (OSError, ValueError, asyncio.IncompleteReadError, asyncio.TimeoutError):
                ok = False
            # the whole answer received
            samples[route].append((time.perf_counter() - started) * 1000)
            if not ok:
                samples["errors"].append(route)
            # a scan, not a JSON parse: the first answer holds the whole history
            elif route == "metrics":
                after = max(map(int, STEP.findall(body)), default=after)
        due += interval
    connection.close()


async def poll_all(
    url: str,
    token: str,
    job: int,
    pollers: int,
    seconds: float,
    interval: float,
    attack_bodies: dict | None = None,
    flood_pause: float = 0.0,
    slow_connections: int = 0,
) -> dict:
    # Answer times (ms) per route, the routes of failed requests, and attack_tasks' results.
    samples: dict[str, Any] = {"job": [], "metrics": [], "errors": [], "attacks": {}}
    # Nothing slow may run between `begin` and the gather: pollers whose first due times have passed
    # fire back to back until they catch up, and that burst, not the server, would be what the tail
    # measures.
    begin = time.monotonic()
    # Spread evenly over one interval, as dashboards opened at different moments.
    tasks = [
        poller(url, token, job, begin + i * interval / pollers, begin + seconds, interval, samples)
        for i in range(pollers)
    ]
    if attack_bodies is not None:
        tasks += attack_tasks(
            url, token, attack_bodies, begin + seconds, samples["attacks"], flood_pause=flood_pause
        )
    if slow_connections:
        tasks += slow_client_tasks(url, token, job, slow_connections, begin + seconds, samples)
    await asyncio.gather(*tasks)
    return samples


def percentiles(values: list[float]) -> dict:
    if not values:
        return {"count": 0}
    a = np.asarray(values)
    return {
        "count": len(a),
        "p50_ms": float(np.percentile(a, 50)),
        "p95_ms": float(np.percentile(a, 95)),
        "p99_ms": float(np.percentile(a, 99)),
        "max_ms": float(a.max()),
    }


def steps_per_s(api: httpx.Client, job: int, seconds: float) -> tuple[float, dict]:
    """The job's training rate over `seconds` (from its reported step), and the job as seen at the
    end."""
    first, started = api.get(f"/v1/jobs/{job}").json(), time.perf_counter()
    time.sleep(seconds)
    last = api.get(f"/v1/jobs/{job}").json()
    return (last["step"] - first["step"]) / (time.perf_counter() - started), last


def poll_cache_counts(api: httpx.Client) -> dict:
    text = api.get("/metrics").text
    counts = {}
    for kind in ("hit", "miss"):
        found = re.search(rf'leco_poll_cache_total{{result="{kind}"}} (\S+)', text)
        if found is None:
            raise RuntimeError(f"/metrics has no leco_poll_cache_total for result={kind!r}")
        counts[kind] = int(float(found.group(1)))
    return counts


def run_loadtest(
    database_url: str | None,
    pollers: int = 200,
    seconds: float = 30.0,
    interval: float = 1.0,
    profile: str = "cpu",
    overrides: dict | None = None,
    data_dir: Path | None = None,
    baseline_s: float = 10.0,
    attack: bool = False,
    flood_pause: float = 0.0,
    slow_connections: int = 0,
) -> dict:
    # seconds of CPU: before any clock
    bodies = build_attack_bodies(scene_archive()) if attack else None
    fit_open_files(pollers + slow_connections)
    with tempfile.TemporaryDirectory() as tmp:
        with (
            Service(Path(data_dir or tmp) / "data", database_url) as service,
            service.client() as api,
        ):
            job = start_job(api, profile, overrides)
            rate_alone, _ = steps_per_s(api, job, baseline_s)  # the training rate nobody polls
            cache_before, started = poll_cache_counts(api), time.perf_counter()
            # this process's own full collections would stall its pollers, not the server
            gc.freeze()
            step_before = api.get(f"/v1/jobs/{job}").json()["step"]
            samples = asyncio.run(
                poll_all(
                    service.url,
                    service.token,
                    job,
                    pollers,
                    seconds,
                    interval,
                    bodies,
                    flood_pause,
                    slow_connections,
                )
            )
            elapsed = time.perf_counter() - started
            after = api.get(f"/v1/jobs/{job}").json()
            cache_after = poll_cache_counts(api)
            api.post(f"/v1/jobs/{job}/cancel")
    requests = len(samples["job"]) + len(samples["metrics"])
    return {
        "database": "postgresql"
        if database_url and database_url.startswith("postgresql")
        else "sqlite",
        "pollers": pollers,
        "seconds": elapsed,
        "interval_s": interval,
        "requests": requests,
        "requests_per_s": requests / elapsed,
        "errors": len(samples["errors"]),
        "all": percentiles(samples["job"] + samples["metrics"]),
        "job": percentiles(samples["job"]),
        "metrics": percentiles(samples["metrics"]),
        "poll_cache": {kind: cache_after[kind] - cache_before[kind] for kind in cache_after},
        "training_steps_during_test": after["step"] - step_before,
        "job_state_after": after["state"],
        "training_steps_per_s": {
            "alone": rate_alone,
            "polled": (after["step"] - step_before) / elapsed,
        },
        **(
            {"attacks": verdict(samples["attacks"]), "flood_pause_s": flood_pause} if attack else {}
        ),
        **(
            {"slow_connections": slow_report(samples, slow_connections)} if slow_connections else {}
        ),
    }


def slow_report(samples: dict, connections: int) -> dict:
    """What the slow clients held and what new clients saw meanwhile."""
    slow, held = samples["slow"], samples["slow"]["held"]
    return {
        "connections": connections,
        "opened": slow["opened"],
        "closed_by_server": slow["closed_by_server"],
        "connect_failures": slow["connect_failures"],
        "held_mean": float(np.mean(held)) if held else 0.0,
        "held_max": max(held, default=0),
        "healthz_fresh_connection": percentiles(samples["healthz"]),
        "job_poll_fresh_connection": percentiles(samples["fresh_poll"]),
    }


@contextmanager
def throwaway_database(admin_url: str):
    """A new PostgreSQL database beside `admin_url`'s, dropped afterwards: the load test's job,
    scene and metrics never land in a database someone uses."""
    from sqlalchemy import create_engine, text
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import SQLAlchemyError

    from service.db import first_line, normalise_url, redact

    admin = create_engine(normalise_url(admin_url), isolation_level="AUTOCOMMIT")
    name = f"leco_loadtest_{os.getpid()}_{secrets.token_hex(4)}"
    try:
        with admin.connect() as connection:
            connection.execute(text(f"CREATE DATABASE {name}"))
    except SQLAlchemyError as error:
        admin.dispose()
        raise SystemExit(
            f"leco loadtest: --postgres {redact(admin_url)}: cannot create a throwaway database "
            f"there: {first_line(error)}"
        ) from None
    try:
        yield (
            make_url(normalise_url(admin_url))
            .set(database=name)
            .render_as_string(hide_password=False)
        )
    finally:
        with admin.connect() as connection:
            connection.execute(text(f"DROP DATABASE IF EXISTS {name} WITH (FORCE)"))
        admin.dispose()


def refuse_used_database(url: str) -> None:
    from sqlalchemy import create_engine, inspect
    from sqlalchemy.engine import make_url

    from service.db import normalise_url, redact

    if make_url(normalise_url(url)).database in ("postgres", "template0", "template1"):
        raise SystemExit(
            f"leco loadtest: {redact(url)} is PostgreSQL's maintenance database: use --postgres "
            f"{redact(url)} to make and drop a throwaway database on that server instead"
        )
    engine = create_engine(normalise_url(url))
    try:
        tables = inspect(engine).get_table_names()
    finally:
        engine.dispose()
    if tables:
        raise SystemExit(
            f"leco loadtest: the database {redact(url)} is not empty (tables: "
            f"{', '.join(sorted(tables)[:5])}{', ...' if len(tables) > 5 else ''}): give an empty "
            "one, or --postgres ADMIN_URL to make and drop a throwaway database on that server"
        )


def loadtest_command(args) -> int:
    if args.pollers < 1 or args.seconds <= 0 or args.interval <= 0 or args.flood_pause < 0:
        raise SystemExit(
            "leco loadtest: --pollers must be at least 1, --seconds and --interval above 0, "
            "--flood-pause at least 0"
        )
    if args.slow_connections < 0:
        raise SystemExit("leco loadtest: --slow-connections must be at least 0")
    attack = {
        "attack": args.attack,
        "flood_pause": args.flood_pause,
        "slow_connections": args.slow_connections,
    }
    if args.postgres:
        with throwaway_database(args.postgres) as url:
            result = run_loadtest(
                url, args.pollers, args.seconds, args.interval, args.profile, **attack
            )
    else:
        if args.database_url:
            refuse_used_database(args.database_url)
        result = run_loadtest(
            args.database_url, args.pollers, args.seconds, args.interval, args.profile, **attack
        )
    print(json.dumps(result, indent=2))
    attacks_ok = all(a["as_expected"] for a in result.get("attacks", {}).values())
    return 0 if result["errors"] == 0 and attacks_ok else 1


def add_commands(commands) -> None:
    load = commands.add_parser(
        "loadtest", help="N concurrent pollers of a training job's status and metrics"
    )
    where = load.add_mutually_exclusive_group()
    where.add_argument(
        "--database-url", default=None, help="an empty database (default: embedded SQLite)"
    )
    where.add_argument(
        "--postgres",
        metavar="ADMIN_URL",
        default=None,
        help="make a throwaway database on this PostgreSQL server, drop it afterwards (e.g. "
        "postgresql://postgres@127.0.0.1:5432/postgres)",
    )
    load.add_argument("--pollers", type=int, default=200)
    load.add_argument("--seconds", type=float, default=30.0, help="how long the pollers run")
    load.add_argument(
        "--interval", type=float, default=1.0, help="each poller's period between polls (s)"
    )
    load.add_argument("--profile", default="cpu", help="profile of the job being trained meanwhile")
    load.add_argument(
        "--attack",
        action="store_true",
        help="meanwhile send hostile uploads (bombs, traversal, no token, a flood of valid "
        "scenes); each must get the 4xx it deserves (bench/attacks.py)",
    )
    load.add_argument(
        "--flood-pause",
        type=float,
        default=0.0,
        metavar="S",
        help="with --attack: each of the 8 flooding clients waits S seconds after an answer "
        "(default 0: back to back, as fast as this machine can send)",
    )
    load.add_argument(
        "--slow-connections",
        type=int,
        default=0,
        metavar="N",
        help="meanwhile hold N connections without a token whose request head never ends "
        "(slowloris), and probe /healthz and a job poll on fresh connections "
        "(bench/slow_clients.py)",
    )
    load.set_defaults(func=loadtest_command)

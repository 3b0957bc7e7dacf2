"""Slow clients for `leco loadtest --slow-connections N`: N connections without a token whose
request head never ends (a header line now and then, as slowloris sends), each opened again as soon
as the server closes it, while probes measure what a new client sees: /healthz and an authenticated
job poll, each on a fresh connection."""

from __future__ import annotations

import asyncio
import resource
import time

DRIP_S = 2.0  # a slow client sends one more header line this often
PROBE_EVERY_S = 0.1


def fit_open_files(connections: int) -> None:
    """This process holds `connections` sockets besides the pollers': raise its soft open-file limit
    to fit."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    need = connections + 1024
    if soft != resource.RLIM_INFINITY and soft < need:
        if hard != resource.RLIM_INFINITY and hard < need:
            raise SystemExit(
                f"leco loadtest: --slow-connections {connections} needs {need} open files; the "
                f"hard limit is {hard}"
            )
        resource.setrlimit(resource.RLIMIT_NOFILE, (need, hard))


async def slow_client(host: str, port: int, until: float, stats: dict) -> None:
    while time.monotonic() < until:
        try:
            reader, writer = await asyncio.open_connection(host, port)
        except OSError:
            stats["connect_failures"] += 1
            await asyncio.sleep(DRIP_S)
            continue
        stats["opened"] += 1
        stats["open"] += 1
        try:
            writer.write(f"GET /v1/jobs HTTP/1.1\r\nHost: {host}:{port}\r\n".encode())
            while time.monotonic() < until:
                try:
                    if await asyncio.wait_for(reader.read(1024), DRIP_S) == b"":
                        stats["closed_by_server"] += 1
                        break
                except asyncio.TimeoutError:
                    writer.write(b"X-Slow: 1\r\n")
        except OSError:
            stats["closed_by_server"] += 1
        finally:
            stats["open"] -= 1
            writer.close()


async def fresh_get(host: str, port: int, target: str, token: str | None) -> tuple[int, float]:
    """(status, ms) of one GET on a new connection: connect, send, read the status line."""
    started = time.perf_counter()
    reader, writer = await asyncio.open_connection(host, port)
    try:
        auth = f"Authorization: Bearer {token}\r\n" if token else ""
        writer.write(
            f"GET {target} HTTP/1.1\r\nHost: {host}:{port}\r\n"
            f"{auth}Connection: close\r\n\r\n".encode()
        )
        status = int((await reader.readline()).split()[1])
        await reader.read()  # the whole answer (the server closes after it)
        return status, (time.perf_counter() - started) * 1000
    finally:
        writer.close()


async def prober(host: str, port: int, token: str, job: int, until: float, samples: dict) -> None:
    due = time.monotonic()
    while due < until:
        await asyncio.sleep(max(0.0, due - time.monotonic()))
        for route, target, auth in (
            ("healthz", "/healthz", None),
            ("fresh_poll", f"/v1/jobs/{job}", token),
        ):
            started = time.perf_counter()
            try:
                status, ms = await asyncio.wait_for(fresh_get(host, port, target, auth), 30)
                ok = status == 200
            except (OSError, ValueError, IndexError, asyncio.TimeoutError):
                ok, ms = False, (time.perf_counter() - started) * 1000
            samples[route].append(ms)
            if not ok:
                samples["errors"].append(route)
        due += PROBE_EVERY_S


async def held_sampler(stats: dict, until: float) -> None:
    """The slow connections open at each half second: whether the attack held what it asked for."""
    while time.monotonic() < until:
        await asyncio.sleep(0.5)
        stats["held"].append(stats["open"])


def slow_client_tasks(
    url: str, token: str, job: int, connections: int, until: float, samples: dict
) -> list:
    host, port = url.split("//", 1)[1].rsplit(":", 1)
    stats = samples.setdefault(
        "slow", {"opened": 0, "open": 0, "closed_by_server": 0, "connect_failures": 0, "held": []}
    )
    samples.setdefault("healthz", [])
    samples.setdefault("fresh_poll", [])
    return [slow_client(host, int(port), until, stats) for _ in range(connections)] + [
        prober(host, int(port), token, job, until, samples),
        held_sampler(stats, until),
    ]

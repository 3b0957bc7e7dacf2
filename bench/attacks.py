"""Hostile uploads for `leco loadtest --attack`: while the pollers run, attackers send what a
careless or hostile client sends, over and over. Every answer must be a 4xx naming the problem
(nothing stored, no 5xx), and the pollers must keep their latency and see no errors."""

from __future__ import annotations

import asyncio
import bz2
import io
import itertools
import tarfile
import time
from pathlib import Path

MiB = 2**20
NAMES = itertools.count(1)
# 429: the scene pool was full (the flood fills it), which is checked before the body is read.
EXPECTED = {
    "no token, 8 MiB body": {401},
    "trailing-data bomb": {422, 429},
    "path traversal": {422, 429},
    "1,300-deep member path": {422, 429},
    "noise": {422, 429},
    "valid scene flood": {201, 429},
}


def _tar(members: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tf:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    return buffer.getvalue()


def attack_bodies(scene_archive: bytes) -> dict[str, tuple[bool, bytes]]:
    """name -> (with the token, body); EXPECTED holds the answers each may get."""
    return {
        "no token, 8 MiB body": (False, bytes(8 * MiB)),
        # 64 MiB of zeros after the tar end marker, compressed to a few hundred bytes
        "trailing-data bomb": (True, bz2.compress(_tar({"scene/a.txt": b"x"}) + bytes(64 * MiB))),
        "path traversal": (True, _tar({"scene/../../evil.txt": b"evil"})),
        "1,300-deep member path": (True, _tar({"scene/" + "d/" * 1300 + "f.txt": b"x"})),
        "noise": (True, bytes(range(256)) * 64),
        # A real scene under fresh names: decoding work in the API process, so the pool fills and
        # answers 429.
        "valid scene flood": (True, scene_archive),
    }


async def post(host: str, port: int, target: str, headers: dict, body: bytes) -> int:
    """POST as curl sends a large body: headers with `Expect: 100-continue` first, the body only
    once the server says 100. A server that refuses at the headers (401, 413, 429) answers without
    ever receiving the body."""
    reader, writer = await asyncio.open_connection(host, port)
    try:
        head = "".join(
            f"{k}: {v}\r\n"
            for k, v in {
                **headers,
                "Host": f"{host}:{port}",
                "Content-Length": str(len(body)),
                "Expect": "100-continue",
                "Connection": "close",
            }.items()
        )
        writer.write(f"POST {target} HTTP/1.1\r\n{head}\r\n".encode())
        status = await read_status(reader)
        if status == 100:
            writer.write(body)
            await writer.drain()
            status = await read_status(reader)
        return status
    finally:
        writer.close()


async def read_status(reader: asyncio.StreamReader) -> int:
    """The status of the next answer; its headers are skipped (a 100's body is empty, a final one is
    not read)."""
    status = int((await reader.readline()).split()[1])
    while (await reader.readline()) not in (b"\r\n", b""):
        pass
    return status


async def attacker(
    url: str,
    token: str,
    kind: str,
    spec: tuple[bool, bytes],
    until: float,
    pause: float,
    results: dict,
) -> None:
    host, port = url.split("//", 1)[1].rsplit(":", 1)
    with_token, body = spec
    headers = {"Authorization": f"Bearer {token}"} if with_token else {}
    while time.monotonic() < until:
        target = f"/v1/scenes/upload?name=attack-{next(NAMES)}"
        try:
            status = await asyncio.wait_for(post(host, int(port), target, headers, body), 60)
        except (OSError, ValueError, IndexError, asyncio.TimeoutError, asyncio.IncompleteReadError):
            status = 0  # no answer at all
        results.setdefault(kind, {}).setdefault(str(status), 0)
        results[kind][str(status)] += 1
        await asyncio.sleep(pause)


def scene_archive() -> bytes:
    """The tiny synthetic city as a tar.gz (generated once into a temporary folder)."""
    import tempfile

    from model.scenes.synthetic import generate

    with tempfile.TemporaryDirectory() as tmp:
        generate("tiny", 0, Path(tmp) / "tiny")
        buffer = io.BytesIO()
        with tarfile.open(fileobj=buffer, mode="w:gz") as tf:
            tf.add(Path(tmp) / "tiny", arcname="scene")
        return buffer.getvalue()


def attack_tasks(
    url: str,
    token: str,
    bodies: dict,
    until: float,
    results: dict,
    flooders: int = 8,
    flood_pause: float = 0.0,
) -> list:
    """One attacker per hostile body (a request every 0.5 s each) and `flooders` uploading valid
    scenes, each waiting `flood_pause` seconds after an answer (0: back to back). `bodies`
    (attack_bodies) are built before the clock starts: building them takes seconds of the load
    generator's CPU."""
    tasks = []
    for kind, spec in bodies.items():
        copies, pause = (flooders, flood_pause) if kind == "valid scene flood" else (1, 0.5)
        tasks += [attacker(url, token, kind, spec, until, pause, results) for _ in range(copies)]
    return tasks


def verdict(results: dict) -> dict:
    """Per attack: the answers seen, and whether every one was one it may get (no 5xx, no lost
    answer)."""
    return {
        kind: {"answers": answers, "as_expected": {int(a) for a in answers} <= EXPECTED[kind]}
        for kind, answers in results.items()
    }

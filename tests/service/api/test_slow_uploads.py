"""Slow upload bodies, against a real uvicorn server: they hold a receiving slot until their
deadline, never a place in the scene pool, so other registrations go on; past the receiving slots
one more is answered 429; a body that stalls is answered 408 and its slot comes back."""

import socket
import time

import httpx
import pytest

from service.api.app import create_app
from service.settings import Settings
from tests.helpers import ON_SQLITE, uvicorn_in_thread

TOKEN = "slow-token"


@pytest.fixture
def server(service_settings):
    settings = Settings(
        **{
            **service_settings.model_dump(),
            "api_tokens": (TOKEN,),
            "scene_workers": 1,
            "scene_queue": 0,
            "upload_receivers": 3,
            "upload_receivers_per_client": 3,
            "upload_idle_s": 1.5,
        }
    )
    app = create_app(settings)
    with uvicorn_in_thread(app, log_level="warning") as port:
        yield port, app


def slow_upload(
    port: int, name: str, source: str = "127.0.0.1", forwarded_for: str | None = None
) -> socket.socket:
    """Headers and the body's first bytes of a 1 MB upload, from the loopback address `source` and
    with an X-Forwarded-For when given; the rest never comes."""
    sock = socket.create_connection(("127.0.0.1", port), source_address=(source, 0))
    forwarded = f"X-Forwarded-For: {forwarded_for}\r\n" if forwarded_for else ""
    sock.sendall(
        f"POST /v1/scenes/upload?name={name} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer "
        f"{TOKEN}\r\nContent-Type: application/octet-stream\r\n{forwarded}"
        "Content-Length: 1000000\r\n\r\n".encode()
        + b"x" * 100
    )
    return sock


def status_of(sock: socket.socket, timeout: float) -> int:
    sock.settimeout(timeout)
    line = sock.recv(4096).split(b"\r\n", 1)[0]
    return int(line.split()[1])


def slots_back(slots, within_s: float = 5.0) -> bool:
    """Whether every receiving slot (and every client's count) comes back within `within_s`."""
    deadline = time.monotonic() + within_s
    while slots.taken and time.monotonic() < deadline:
        time.sleep(0.05)
    return slots.taken == 0 and slots.by_client == {}


def test_slow_uploads_hold_no_pool_place_and_are_cut_off_at_their_deadline(server):
    port, app = server
    slow = [slow_upload(port, f"slow-{i}") for i in range(3)]
    try:
        time.sleep(0.3)
        assert app.state.upload_slots.taken == 3
        with httpx.Client(
            base_url=f"http://127.0.0.1:{port}",
            headers={"Authorization": f"Bearer {TOKEN}"},
            timeout=10,
        ) as client:
            fourth = client.post(
                "/v1/scenes/upload", params={"name": "fourth"}, content=b"y" * 1000
            )
            assert fourth.status_code == 429 and "uploads are being received" in fourth.text
            # The pool's one place is free while three bodies trickle in: a registration takes it.
            started = time.monotonic()
            synthetic = client.post("/v1/scenes/synthetic", json={"preset": "tiny", "seed": 0})
            assert synthetic.status_code == 202, synthetic.text
            assert time.monotonic() - started < 1.0
        for sock in slow:  # each is cut off once it has sent nothing for upload_idle_s
            assert status_of(sock, timeout=10) == 408
    finally:
        for sock in slow:
            sock.close()
    assert slots_back(app.state.upload_slots)


def test_one_client_may_hold_only_so_many_receiving_slots(service_settings):
    settings = Settings(
        **{
            **service_settings.model_dump(),
            "api_tokens": (TOKEN,),
            "upload_receivers": 3,
            "upload_receivers_per_client": 2,
            "upload_idle_s": 1.5,
        }
    )
    app = create_app(settings)
    with uvicorn_in_thread(app, log_level="warning") as port:
        slow = [slow_upload(port, f"slow-{i}") for i in range(2)]
        try:
            time.sleep(0.3)
            third = slow_upload(port, "third")
            assert status_of(third, timeout=5) == 429
            third.close()
            assert app.state.upload_slots.taken == 2 and app.state.upload_slots.by_client == {
                "127.0.0.1": 2
            }
        finally:
            for sock in slow:
                sock.close()
        assert slots_back(app.state.upload_slots)


def counted(slots, clients: dict, within_s: float = 5.0) -> dict:
    """The receiving slots' count by client once it is `clients` (or after `within_s`)."""
    deadline = time.monotonic() + within_s
    while slots.by_client != clients and time.monotonic() < deadline:
        time.sleep(0.05)
    return dict(slots.by_client)


@ON_SQLITE
def test_a_forwarded_address_is_counted_only_from_a_trusted_proxy(service_settings):
    """`leco serve --trusted-proxies` (127.0.0.1 by default) names the peers whose X-Forwarded-For
    names the client. Another peer (127.0.0.2 here) writing one is counted as itself by the
    per-client cap: a second upload under another forwarded name is still its second (429). The
    trusted proxy's forwarded clients are counted apart."""
    import argparse

    from cli.serve import add_commands

    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers())
    trusted = parser.parse_args(["serve"]).trusted_proxies
    assert trusted == "127.0.0.1"
    settings = Settings(
        **{
            **service_settings.model_dump(),
            "api_tokens": (TOKEN,),
            "upload_receivers": 4,
            "upload_receivers_per_client": 1,
            "upload_idle_s": 10.0,  # no upload is cut off before the counts are read
        }
    )
    app = create_app(settings)
    slots = app.state.upload_slots
    # what `leco serve` gives uvicorn (cli/serve.py)
    config = {"proxy_headers": True, "forwarded_allow_ips": trusted}
    with uvicorn_in_thread(app, log_level="warning", **config) as port:
        spoofed = slow_upload(port, "spoofed", source="127.0.0.2", forwarded_for="203.0.113.1")
        held = [spoofed]
        try:
            assert counted(slots, {"127.0.0.2": 1}) == {"127.0.0.2": 1}
            again = slow_upload(port, "again", source="127.0.0.2", forwarded_for="203.0.113.2")
            held.append(again)
            assert status_of(again, timeout=5) == 429
            held += [
                slow_upload(port, f"proxied-{i}", forwarded_for=f"198.51.100.{i}") for i in (1, 2)
            ]
            clients = {"127.0.0.2": 1, "198.51.100.1": 1, "198.51.100.2": 1}
            assert counted(slots, clients) == clients
        finally:
            for sock in held:
                sock.close()
        assert slots_back(slots)


def test_the_per_client_cap_counts_each_address_apart_and_the_total_still_binds():
    from fastapi import HTTPException

    from service.api.receiving import ReceivingSlots

    slots = ReceivingSlots(limit=3, per_client=2)
    with slots.slot("10.0.0.1"), slots.slot("10.0.0.1"):
        with pytest.raises(HTTPException, match="this client already sends 2 uploads"):
            with slots.slot("10.0.0.1"):
                pass
        with slots.slot("10.0.0.2"):  # another client still gets the last slot
            with pytest.raises(HTTPException, match="3 uploads are being received"):
                with slots.slot("10.0.0.3"):
                    pass
    assert slots.taken == 0 and slots.by_client == {}


def receive(chunks, gap_s: float, **limits):
    import asyncio
    import io

    from service.api.receiving import receive_body

    async def body():
        for chunk in chunks:
            await asyncio.sleep(gap_s)
            yield chunk

    into = io.BytesIO()
    return asyncio.run(
        receive_body(
            body(), into, **{"max_bytes": 10_000, "idle_s": 0.3, "min_bytes_per_s": 0.0, **limits}
        )
    ), into.getvalue()


def test_a_trickling_body_is_refused_and_a_steady_one_is_received_whole():
    from fastapi import HTTPException

    assert receive([b"ab", b"cd", b"e"], gap_s=0.01) == (5, b"abcde")
    with pytest.raises(HTTPException) as trickle:  # never idle for 0.3 s, but 1 byte per 0.1 s
        receive([b"x"] * 10, gap_s=0.1, min_bytes_per_s=100.0)
    assert trickle.value.status_code == 408 and "averaged" in trickle.value.detail
    with pytest.raises(HTTPException) as stalled:
        receive([b"x", b"y"], gap_s=0.5)
    assert stalled.value.status_code == 408 and "sent nothing for 0.3 s" in stalled.value.detail
    with pytest.raises(HTTPException) as big:
        receive([b"x" * 6000] * 2, gap_s=0.0)
    assert big.value.status_code == 413


def test_a_json_body_that_trickles_is_cut_off_and_the_server_answers_others(server):
    """A job request whose body stops after 11 of 200 bytes is answered 408 after upload_idle_s
    (1.5 s here), and the connection closed; meanwhile other requests are answered."""
    port, _ = server
    sock = socket.create_connection(("127.0.0.1", port))
    try:
        sock.sendall(
            f"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {TOKEN}\r\n"
            'Content-Type: application/json\r\nContent-Length: 200\r\n\r\n{"scene": 1'.encode()
        )
        started = time.monotonic()
        health = httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=5)
        assert health.status_code == 200
        sock.settimeout(10)
        # read to the end of the stream: the headers and the body may come in separate segments
        answer, chunk = b"", sock.recv(4096)
        while chunk:
            answer, chunk = answer + chunk, sock.recv(4096)
        assert int(answer.split(b"\r\n", 1)[0].split()[1]) == 408
        assert b"sent nothing for 1.5 s after 11 bytes" in answer
        assert 1.2 < time.monotonic() - started < 6
    finally:
        sock.close()


@ON_SQLITE
def test_a_json_body_under_the_minimum_rate_is_cut_off_and_its_connection_closed(server):
    """A job request whose body never pauses for upload_idle_s (a byte every 0.1 s) but past its
    first 1.5 s averages under LECO_UPLOAD_MIN_BYTES_PER_S (16 KiB/s) is answered 408 naming the
    rate, and the server closes the connection (the rest of the body is not read)."""
    import select

    port, _ = server
    sock = socket.create_connection(("127.0.0.1", port))
    try:
        sock.sendall(
            f"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {TOKEN}\r\n"
            "Content-Type: application/json\r\nContent-Length: 200\r\n\r\n{".encode()
        )
        started, sent = time.monotonic(), 1
        # one byte at a time until the server answers (the 200 bytes would take 20 s)
        while not select.select([sock], [], [], 0.1)[0] and sent < 200:
            sock.sendall(b" ")
            sent += 1
        waited = time.monotonic() - started
        sock.settimeout(10)
        # read to the end of the stream: a connection left open would time out here
        answer, chunk = b"", sock.recv(4096)
        while chunk:
            answer, chunk = answer + chunk, sock.recv(4096)
        assert int(answer.split(b"\r\n", 1)[0].split()[1]) == 408, answer
        assert b"bytes/s; at least 16,384 are needed" in answer
        assert b"connection: close" in answer.lower()
        assert 1.4 < waited < 8, waited  # past the first upload_idle_s, long before the body ends
        assert sent < 100
    finally:
        sock.close()


def trickling_job_request(port: int, token: str) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port))
    sock.sendall(
        f"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n"
        "Content-Type: application/json\r\nContent-Length: 200\r\n\r\n{".encode()
    )
    return sock


def test_one_token_holds_at_most_its_share_of_unfinished_requests(service_settings):
    settings = Settings(
        **{
            **service_settings.model_dump(),
            "api_tokens": (TOKEN, "other-token"),
            "upload_idle_s": 1.5,
            "max_requests_per_token": 2,
        }
    )
    with uvicorn_in_thread(create_app(settings), log_level="warning") as port:
        held = [trickling_job_request(port, TOKEN) for _ in range(2)]
        try:
            time.sleep(0.3)
            url = f"http://127.0.0.1:{port}/v1/jobs"
            third = httpx.get(url, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=5)
            assert third.status_code == 429 and "2 requests unfinished" in third.text
            other = httpx.get(url, headers={"Authorization": "Bearer other-token"}, timeout=5)
            assert other.status_code == 200  # another token is not held up
            assert [status_of(s, 10) for s in held] == [408, 408]
            again = httpx.get(url, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=5)
            assert again.status_code == 200  # their places came back
        finally:
            for sock in held:
                sock.close()

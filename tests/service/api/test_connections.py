"""`leco serve`'s connection hygiene against a real uvicorn server: request headers that do not
arrive in time close the connection (on a fresh connection and on a kept-alive one), a request whose
headers did arrive is not cut by that deadline, at the cap a new connection evicts the oldest one
still owing its head (or is closed when every connection is inside a request), and the open-file
limit is raised to fit the cap."""

import resource
import socket
import time

import pytest

from service.api.connections import RESERVED_FDS, connection_budget, guarded_protocol
from tests.helpers import uvicorn_in_thread

DEADLINE_S = 0.5
CAP = 8


async def app(scope, receive, send):
    """Answers after reading the whole body: a slow body keeps its request open."""
    if scope["type"] != "http":
        return
    more = True
    while more:
        more = (await receive()).get("more_body", False)
    await send(
        {"type": "http.response.start", "status": 200, "headers": [(b"content-length", b"2")]}
    )
    await send({"type": "http.response.body", "body": b"ok"})


@pytest.fixture(scope="module")
def server():
    protocol = guarded_protocol(DEADLINE_S, CAP)
    with uvicorn_in_thread(app, log_level="critical", http=protocol, timeout_keep_alive=30) as port:
        yield port, protocol


def closed_within(sock: socket.socket, seconds: float) -> float | None:
    """Seconds until the server closed the socket (None: still open after `seconds`)."""
    started = time.monotonic()
    sock.settimeout(seconds)
    try:
        while data := sock.recv(4096):
            # an answer may come first on a kept-alive connection
            assert b"HTTP/1.1" in data or data
    except TimeoutError:
        return None
    except ConnectionResetError:
        pass
    return time.monotonic() - started


def get(sock: socket.socket) -> bytes:
    sock.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
    sock.settimeout(5)
    return sock.recv(4096)


def wait_idle(protocol, port):
    """Until the server holds no connection of the test before (each test starts from an empty
    server)."""
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
        with socket.create_connection(("127.0.0.1", port)) as probe:
            if get(probe).startswith(b"HTTP/1.1 200"):
                return
        time.sleep(0.1)


def test_headers_that_never_end_are_closed_at_the_deadline_while_others_are_answered(server):
    port, protocol = server
    before = protocol.timed_out
    with socket.create_connection(("127.0.0.1", port)) as slow:
        slow.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n")  # no blank line: the head never ends
        with socket.create_connection(("127.0.0.1", port)) as quick:
            assert get(quick).startswith(b"HTTP/1.1 200")
        for _ in range(3):  # a header line now and then does not buy more time
            time.sleep(DEADLINE_S / 4)
            try:
                slow.sendall(b"X-Slow: 1\r\n")
            except OSError:
                break
        took = closed_within(slow, 5)
    assert took is not None and took < DEADLINE_S * 2, took
    assert protocol.timed_out == before + 1


def test_a_kept_alive_connection_owes_its_next_headers_in_time(server):
    port, _ = server
    with socket.create_connection(("127.0.0.1", port)) as sock:
        assert get(sock).startswith(b"HTTP/1.1 200")
        sock.sendall(b"GET / HTTP/1.1\r\n")
        assert closed_within(sock, 5) is not None


def test_a_request_whose_headers_arrived_is_not_cut_by_the_header_deadline(server):
    port, _ = server
    with socket.create_connection(("127.0.0.1", port)) as sock:
        sock.sendall(b"POST / HTTP/1.1\r\nHost: x\r\nContent-Length: 4\r\n\r\nab")
        time.sleep(DEADLINE_S * 3)
        sock.sendall(b"cd")
        sock.settimeout(5)
        assert sock.recv(4096).startswith(b"HTTP/1.1 200")


def test_at_the_cap_real_requests_evict_the_oldest_slow_heads(server):
    port, protocol = server
    wait_idle(protocol, port)
    before = protocol.evicted
    slow = [socket.create_connection(("127.0.0.1", port)) for _ in range(CAP)]
    try:
        for s in slow:
            s.sendall(b"GET / HTTP/1.1\r\n")
        time.sleep(0.1)
        quick = []
        for _ in range(4):  # each new connection takes the place of the oldest head still owed
            quick.append(socket.create_connection(("127.0.0.1", port)))
            assert get(quick[-1]).startswith(b"HTTP/1.1 200")
        for q in quick:
            q.close()
        assert protocol.evicted - before == 4
        assert all(closed_within(s, 1) is not None for s in slow[:4])  # the oldest went first
    finally:
        for s in slow:
            s.close()
    wait_idle(protocol, port)


def test_at_the_cap_with_every_connection_in_a_request_a_new_one_is_closed(server):
    port, protocol = server
    wait_idle(protocol, port)
    before = protocol.refused
    busy = [socket.create_connection(("127.0.0.1", port)) for _ in range(CAP)]
    try:
        for s in busy:  # heads complete, bodies pending: requests, not slow heads
            s.sendall(b"POST / HTTP/1.1\r\nHost: x\r\nContent-Length: 4\r\n\r\nab")
        time.sleep(0.2)
        with socket.create_connection(("127.0.0.1", port)) as extra:
            assert closed_within(extra, 1) is not None
        assert protocol.refused == before + 1
        for s in busy:  # the requests in progress were not touched
            s.sendall(b"cd")
            s.settimeout(5)
            assert s.recv(4096).startswith(b"HTTP/1.1 200")
    finally:
        for s in busy:
            s.close()
    wait_idle(protocol, port)  # once they are gone, connections are served again


def test_the_open_file_limit_is_raised_to_fit_the_cap():
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < 2 * RESERVED_FDS + 64:
        pytest.skip(f"hard open-file limit {hard} is too low to test raising the soft one")
    low = RESERVED_FDS + 32
    resource.setrlimit(resource.RLIMIT_NOFILE, (low, hard))
    try:
        wanted = 64 if hard == resource.RLIM_INFINITY else min(1000, hard - RESERVED_FDS)
        assert connection_budget(wanted) == wanted
        assert resource.getrlimit(resource.RLIMIT_NOFILE)[0] == wanted + RESERVED_FDS
        if hard != resource.RLIM_INFINITY:  # more than the hard limit allows: what fits under it
            assert connection_budget(hard) == hard - RESERVED_FDS
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))

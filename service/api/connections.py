"""Connection hygiene for `leco serve` when no reverse proxy stands in front (docker-compose and
KubeRay put nginx there, deploy/nginx.conf.template): uvicorn has no deadline for a request's
headers and no cap on connections, so a client that opens connections and never finishes their
headers holds them, and file descriptors, for as long as it likes. This protocol closes a connection
whose request head is not complete within `header_timeout_s` (drawn between half of it and all of
it) after it opened or after its previous response, and holds at most `max_connections`, keeping the
process clear of its open-file limit (which Ray raises to the hard limit) however many slow clients
come. Bodies have their own deadlines (service/api/receiving.py)."""

from __future__ import annotations

import asyncio
import logging
import random
import resource
from collections import OrderedDict

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

log = logging.getLogger("leco.api")
# files the process needs besides its connections: databases, artefacts, pool pipes, logs
RESERVED_FDS = 256


def connection_budget(wanted: int) -> int:
    """Raise the soft open-file limit towards `wanted` + RESERVED_FDS (up to the hard limit) and
    return how many connections fit under it."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    need = wanted + RESERVED_FDS
    if soft != resource.RLIM_INFINITY and soft < need:
        target = need if hard == resource.RLIM_INFINITY else min(need, hard)
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
        soft = target
    fits = wanted if soft == resource.RLIM_INFINITY else min(wanted, soft - RESERVED_FDS)
    if fits < wanted:
        log.warning(
            "open-file limit %d: accepting at most %d connections, not %d", soft, fits, wanted
        )
    return max(fits, 1)


def guarded_protocol(header_timeout_s: float, max_connections: int) -> type[H11Protocol]:
    """uvicorn's h11 protocol with a header deadline and a connection cap
    (uvicorn.Config(http=...)). At the cap a new connection evicts the oldest one still waiting for
    its request head, if any: a real client sends its head at once and is never the oldest, so a
    flood of slow heads churns while real requests get in. Only when every connection is inside a
    request is the new one closed."""
    # connections owing a request head, oldest first
    waiting: OrderedDict[H11Protocol, None] = OrderedDict()

    class GuardedH11Protocol(H11Protocol):
        refused = 0  # new connections closed because max_connections were busy with requests
        evicted = 0  # connections owing their request head, closed at the cap to let a new one in
        timed_out = 0  # connections closed for request heads that did not arrive in time
        _header_deadline: asyncio.TimerHandle | None = None

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            if len(self.connections) > max_connections:
                if not waiting:
                    GuardedH11Protocol.refused += 1
                    transport.abort()  # no answer: answering costs what the cap is there to save
                    return
                oldest, _ = waiting.popitem(last=False)
                GuardedH11Protocol.evicted += 1
                oldest.transport.abort()
            self._owe_head()

        def handle_events(self) -> None:
            super().handle_events()
            if self.conn.their_state is not h11.IDLE:  # a complete request head has arrived
                self._disarm_header_deadline()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if not self.transport.is_closing():
                self._owe_head()  # a keep-alive connection owes the next request's head in time

        def connection_lost(self, exc: Exception | None) -> None:
            self._disarm_header_deadline()
            super().connection_lost(exc)

        def _owe_head(self) -> None:
            self._disarm_header_deadline()
            waiting[self] = None
            # Between half the deadline and all of it: slow clients that came together do not all
            # leave (and come back) in the same instant, which made a burst of latency for everyone
            # else every header_timeout_s.
            delay = header_timeout_s * (0.5 + 0.5 * random.random())
            self._header_deadline = self.loop.call_later(delay, self._head_overdue)

        def _disarm_header_deadline(self) -> None:
            waiting.pop(self, None)
            if self._header_deadline is not None:
                self._header_deadline.cancel()
                self._header_deadline = None

        def _head_overdue(self) -> None:
            self._header_deadline = None
            waiting.pop(self, None)
            # Their side is still IDLE until a complete request head has been parsed; past it (a
            # body being sent, a response being written) the connection is some request's and other
            # deadlines govern it.
            if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
                GuardedH11Protocol.timed_out += 1
                self.transport.abort()

    return GuardedH11Protocol

"""An upload's body is received before it takes any place in the scene pool, in a bounded number of
receiving slots, and a client that sends too slowly is cut off. So slow uploads hold a receiving
slot at most for the deadline, never the pool's places: registrations of others go on (the pool is
reserved once the body is in).

A slot is given back however the request ends: body complete, refused, timed out or the client
gone."""

from __future__ import annotations

import asyncio
import threading
import time
from contextlib import contextmanager
from typing import IO, AsyncIterator, Iterator

from fastapi import HTTPException

from service.workpool import RETRY_AFTER_S


class ReceivingSlots:
    """At most `limit` bodies being received at once, and at most `per_client` from one client
    address; one more is answered 429 at once (no waiting). The per-client cap keeps one client's
    slow uploads from taking every slot (behind a proxy the address is the one it forwards:
    uvicorn's proxy headers)."""

    def __init__(self, limit: int, per_client: int | None = None):
        self.limit, self.per_client = limit, per_client or limit
        self.taken, self._lock = 0, threading.Lock()
        self.by_client: dict[str, int] = {}

    @contextmanager
    def slot(self, client: str = "") -> Iterator[None]:
        with self._lock:
            if self.taken >= self.limit:
                raise HTTPException(
                    429,
                    f"{self.limit} uploads are being received, the most this server takes at once; "
                    f"retry in {RETRY_AFTER_S} s",
                    headers={"retry-after": str(RETRY_AFTER_S)},
                )
            if self.by_client.get(client, 0) >= self.per_client:
                raise HTTPException(
                    429,
                    f"this client already sends {self.per_client} uploads, the most one client may "
                    f"send at once; retry once one is in (in {RETRY_AFTER_S} s)",
                    headers={"retry-after": str(RETRY_AFTER_S)},
                )
            self.taken += 1
            self.by_client[client] = self.by_client.get(client, 0) + 1
        try:
            yield
        finally:
            with self._lock:
                self.taken -= 1
                self.by_client[client] -= 1
                if not self.by_client[client]:
                    # the map holds only clients sending now: bounded by `limit`
                    del self.by_client[client]


async def receive_body(
    chunks: AsyncIterator[bytes],
    into: IO[bytes],
    max_bytes: int,
    idle_s: float,
    min_bytes_per_s: float,
) -> int:
    """Writes the body to `into` and returns its size. Refuses (408) a body that sends nothing for
    `idle_s`, or that once past its first `idle_s` averages under `min_bytes_per_s`; 413 past
    `max_bytes`."""
    start, size = time.monotonic(), 0
    iterator = chunks.__aiter__()
    while True:
        try:
            chunk = await asyncio.wait_for(iterator.__anext__(), timeout=idle_s)
        except StopAsyncIteration:
            return size
        except asyncio.TimeoutError:
            raise HTTPException(
                408,
                f"the upload sent nothing for {idle_s:g} s after {size:,} bytes: send the body "
                "without pauses",
            ) from None
        size += len(chunk)
        if size > max_bytes:
            raise HTTPException(413, f"upload exceeds the limit of {max_bytes} bytes")
        into.write(chunk)
        elapsed = time.monotonic() - start
        if elapsed > idle_s and size / elapsed < min_bytes_per_s:
            raise HTTPException(
                408,
                f"the upload averaged {size / elapsed:,.0f} bytes/s over {elapsed:.0f} s; at least "
                f"{min_bytes_per_s:,.0f} are needed",
            )

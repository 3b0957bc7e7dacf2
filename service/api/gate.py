"""The door of /v1, before any route reads a byte of the body: the bearer token first (401), then
the body's size (413) and, for bodies the route does not stream, the uploads' deadlines (408:
nothing for LECO_UPLOAD_IDLE_S, or under LECO_UPLOAD_MIN_BYTES_PER_S once past it); and for every
route, no NUL byte in the path or query string (422). FastAPI parses a JSON body before it runs a
route's dependencies, so a token check there let a request with no token and a malformed or huge
body get 422, buffered and parsed whole. This is the only token check. A plain ASGI middleware, like
RequestStats, so polling pays nothing for it."""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import json
import re
import time
from collections import Counter

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.settings import Settings
from service.workpool import RETRY_AFTER_S

MAX_JSON_BODY = 64 * 1024  # a job request with every override is a few KiB
# A render's body may carry a camera path of up to workers/render/schemas.py's MAX_FRAMES (1,200)
# cameras, each a 4x4 matrix and intrinsics at full float precision (about 600 bytes in JSON, 1 KiB
# with room for a nerfstudio frame's extra keys). Not imported from there: that module loads torch,
# the API does not.
PATH_CAMERAS, CAMERA_JSON_BYTES = 1200, 1024
MAX_PATH_BODY = MAX_JSON_BODY + PATH_CAMERAS * CAMERA_JSON_BYTES
CARRIES_A_PATH = re.compile(r"^/v1/jobs/[^/]+/renders$")
CLOSE = {"connection": "close"}  # a refused body's remaining bytes are not read
# the route streams its body and caps it at LECO_MAX_UPLOAD_BYTES
STREAMED = {("POST", "/v1/scenes/upload"), ("POST", "/v1/scenes/photos")}
# take a place in the scene pool
REGISTERS = {
    ("POST", "/v1/scenes/upload"),
    ("POST", "/v1/scenes/photos"),
    ("POST", "/v1/scenes/synthetic"),
}


def token_ok(tokens: tuple[str, ...], authorization: str) -> bool:
    if not tokens:
        return True
    scheme, _, given = authorization.partition(" ")
    # Constant time, and every configured token is compared, so timing says nothing about which one
    # nearly matched.
    matched = False
    for token in tokens:
        matched |= hmac.compare_digest(given.strip().encode(), token.encode())
    return scheme.lower() == "bearer" and matched


class Gatekeeper:
    def __init__(self, app: ASGIApp) -> None:
        self.app = app
        # unfinished /v1 requests by token (a hash of the Authorization header: no token is kept)
        self.in_flight: Counter[str] = Counter()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        query = scope.get("query_string", b"").lower()
        if "\0" in scope["path"] or b"%00" in query or b"\0" in query:
            # No name, id or filter of ours holds a NUL, and PostgreSQL refuses one in any string (a
            # 500).
            return await answer(send, 422, "the request's path or query string holds a NUL byte")
        if not scope["path"].startswith("/v1/"):
            return await self.app(scope, receive, send)
        settings = scope["app"].state.settings
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        if not token_ok(settings.api_tokens, headers.get("authorization", "")):
            return await answer(
                send,
                401,
                "missing or invalid bearer token (send 'Authorization: Bearer <token>')",
                {"www-authenticate": "Bearer"},
            )
        holder = hashlib.sha256(headers.get("authorization", "").encode()).hexdigest()
        if self.in_flight[holder] >= settings.max_requests_per_token:
            return await answer(
                send,
                429,
                f"this token has {settings.max_requests_per_token} requests unfinished "
                "(LECO_MAX_REQUESTS_PER_TOKEN); wait for their answers",
                {"retry-after": str(RETRY_AFTER_S)},
            )
        self.in_flight[holder] += 1
        try:
            return await self.admitted(scope, receive, send, settings, headers)
        finally:
            self.in_flight[holder] -= 1
            if not self.in_flight[holder]:
                del self.in_flight[holder]

    async def admitted(
        self, scope: Scope, receive: Receive, send: Send, settings: Settings, headers: dict
    ) -> None:
        route = (scope["method"], scope["path"])
        if route in REGISTERS and scope["app"].state.scene_pool.full:
            # The route refuses too (admission decides); here a client that floods without backing
            # off costs the event loop a header parse, not a trip through routing, validation and
            # the exception handler.
            busy = scope["app"].state.scene_pool.busy()
            return await answer(send, 429, str(busy), {"retry-after": str(RETRY_AFTER_S)})
        streamed = route in STREAMED
        limit = (
            settings.max_upload_bytes
            if streamed
            else MAX_PATH_BODY
            if scope["method"] == "POST" and CARRIES_A_PATH.match(scope["path"])
            else MAX_JSON_BODY
        )
        declared = headers.get("content-length", "")
        if declared and (not declared.isdigit() or int(declared) > limit):
            return await answer(
                send, 413, f"request body is {declared} bytes; the limit here is {limit}"
            )
        if streamed:
            return await self.app(scope, receive, send)
        chunks, size, more = [], 0, True
        idle_s, min_rate = settings.upload_idle_s, settings.upload_min_bytes_per_s
        started = time.monotonic()
        # small bodies only: read to the end (or past the limit) before the route sees any of it,
        # under the uploads' deadlines, so a body that trickles in cannot hold a connection
        while more:
            try:
                message = await asyncio.wait_for(receive(), timeout=idle_s)
            except TimeoutError:
                return await answer(
                    send,
                    408,
                    f"the request body sent nothing for {idle_s:g} s after {size:,} bytes: send "
                    "the body without pausing",
                    CLOSE,
                )
            if message["type"] == "http.disconnect":
                return
            chunks.append(message.get("body", b""))
            size += len(chunks[-1])
            more = message.get("more_body", False)
            if size > limit:
                return await answer(
                    send, 413, f"request body exceeds the limit of {limit} bytes here"
                )
            elapsed = time.monotonic() - started
            if more and elapsed > idle_s and size / elapsed < min_rate:
                return await answer(
                    send,
                    408,
                    f"the request body arrived at {size / elapsed:,.0f} bytes/s; at least "
                    f"{min_rate:,.0f} are needed",
                    CLOSE,
                )
        body, replayed = b"".join(chunks), False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        return await self.app(scope, replay, send)


async def answer(send: Send, status: int, detail: str, headers: dict | None = None) -> None:
    payload = json.dumps({"detail": detail}).encode()
    raw = [(b"content-type", b"application/json"), (b"content-length", str(len(payload)).encode())]
    raw += [(k.encode(), v.encode()) for k, v in (headers or {}).items()]
    await send({"type": "http.response.start", "status": status, "headers": raw})
    await send({"type": "http.response.body", "body": payload})

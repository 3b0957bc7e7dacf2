"""What every route needs: the settings, and bearer-token auth on /v1 when tokens are configured."""

from __future__ import annotations

import hmac

from typing import Annotated

from fastapi import HTTPException, Path, Request

from service.api.poll_cache import PollCache
from service.settings import Settings


# Both are `async def` although they wait for nothing: FastAPI runs a plain `def` dependency in its threadpool,
# a thread hop per request that a poll-heavy API cannot afford.
async def settings_of(request: Request) -> Settings:
    return request.app.state.settings


def poll_cache_of(request: Request) -> PollCache:
    return request.app.state.poll_cache


async def require_token(request: Request) -> None:
    tokens = request.app.state.settings.api_tokens
    if not tokens:
        return
    scheme, _, given = request.headers.get("authorization", "").partition(" ")
    # Constant time, and every configured token is compared, so timing says nothing about which one nearly matched.
    matched = False
    for token in tokens:
        matched |= hmac.compare_digest(given.strip().encode(), token.encode())
    if scheme.lower() != "bearer" or not matched:
        raise HTTPException(401, "missing or invalid bearer token (send 'Authorization: Bearer <token>')",
                            headers={"WWW-Authenticate": "Bearer"})


def not_found(what: str, ident) -> HTTPException:
    return HTTPException(404, f"{what} {ident!r} not found")


# Row ids and steps are 32-bit integers in PostgreSQL (64-bit in SQLite): a larger number in a path or query is
# answered 422 by validation, never handed to the database driver to overflow.
MAX_INT = 2**31 - 1
RowId = Annotated[int, Path(ge=1, le=MAX_INT)]

"""What every route needs: the settings, the poll cache and the scene pool
(bearer-token auth is service/api/gate.py)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Path, Request

from service.api.poll_cache import PollCache
from service.settings import Settings
from service.workpool import WorkPool


# Both are `async def` although they wait for nothing: FastAPI runs a plain `def` dependency in its
# threadpool, a thread hop per request that a poll-heavy API cannot afford.
async def settings_of(request: Request) -> Settings:
    return request.app.state.settings


# A route's settings, as a FastAPI dependency (a test can override `settings_of`).
SettingsDep = Annotated[Settings, Depends(settings_of)]


def poll_cache_of(request: Request) -> PollCache:
    return request.app.state.poll_cache


def scene_pool_of(request: Request) -> WorkPool:
    return request.app.state.scene_pool


def not_found(what: str, ident: object) -> HTTPException:
    return HTTPException(404, f"{what} {ident!r} not found")


# Row ids and steps are 32-bit integers in PostgreSQL (64-bit in SQLite): a larger number in a path
# or query is answered 422 by validation, never handed to the database driver to overflow.
MAX_INT = 2**31 - 1
RowId = Annotated[int, Path(ge=1, le=MAX_INT)]

"""The FastAPI application. It refuses to start on a database whose schema is not the one this code
needs."""

from __future__ import annotations

import logging
import time
from collections import Counter
from contextlib import asynccontextmanager
from typing import AsyncIterator

from fastapi import APIRouter, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from sqlalchemy.exc import InterfaceError, OperationalError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from model.errors import LecoError
from service.api import (
    artifacts,
    camera_paths,
    dashboard,
    docs,
    health,
    job_kinds,
    jobs,
    methods,
    scenes,
    work,
)
from service.api.gate import Gatekeeper
from service.api.headers import SecurityHeaders
from service.api.poll_cache import PollCache
from service.api.receiving import ReceivingSlots
from service.db import check_schema, first_line
from service.settings import Settings
from service.workpool import RETRY_AFTER_S, WorkPool

# An error's detail is a sentence: a message that quotes a user's file or body is cut here, whatever
# built it.
MAX_DETAIL_CHARS = 1000
MAX_VALIDATION_ERRORS = 20


def bounded(detail: object) -> object:
    if isinstance(detail, str) and len(detail) > MAX_DETAIL_CHARS:
        return (
            detail[:MAX_DETAIL_CHARS] + f"... ({len(detail) - MAX_DETAIL_CHARS:,} more characters)"
        )
    return detail


log = logging.getLogger("leco.api")
# The HTTP status of each kind of error (model/errors.py), and the kinds worth retrying.
STATUSES = {"invalid": 422, "conflict": 409, "busy": 429, "unavailable": 503, "failed": 500}
RETRY_KINDS = ("busy", "unavailable")
# /metrics labels come from fixed sets: any other method a client sends counts as "other", a path no
# route matches as "unmatched", so requests cannot add labels (series) without bound
HTTP_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})


class RequestStats:
    """Counts requests by (method, route, status) and the time spent answering them, for /metrics. A
    plain ASGI middleware: Starlette's BaseHTTPMiddleware costs about a millisecond per request,
    which a poll-heavy API cannot afford."""

    def __init__(self, app: ASGIApp, stats: dict) -> None:
        self.app, self.stats = app, stats

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        started, status = time.perf_counter(), 500

        async def send_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            route = scope.get("route")
            method = scope["method"] if scope["method"] in HTTP_METHODS else "other"
            self.stats["count"][(method, getattr(route, "path", "unmatched"), str(status))] += 1
            self.stats["seconds"] += time.perf_counter() - started


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings.from_env()
    check_schema(settings.db_url)  # raises SchemaError naming the command to run

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        yield
        app.state.scene_pool.close()  # its worker processes end with the server
        app.state.view_pool.close()

    app = FastAPI(
        title="LeCO-NeRF Service",
        version="1",
        lifespan=lifespan,
        # FastAPI's pages load Swagger UI and ReDoc from a CDN; ours serves them itself (docs.py)
        docs_url=None,
        redoc_url=None,
        description="Register scenes, submit LeCO-NeRF / Switch-NeRF / occupancy-grid training "
        "jobs, follow their metrics, download their artifacts.",
    )
    app.state.settings = settings
    app.state.http_stats = {"count": Counter(), "seconds": 0.0, "started": time.monotonic()}
    app.state.poll_cache = PollCache(settings.poll_cache_s)
    app.state.scene_pool = WorkPool(
        settings.scene_workers, settings.scene_queue, "scene registrations"
    )
    app.state.upload_slots = ReceivingSlots(
        settings.upload_receivers, settings.upload_receivers_per_client
    )
    app.state.view_pool = WorkPool(settings.view_workers, settings.view_queue, "view renders")
    app.state.view_cache = work.ViewCache(work.VIEW_CACHE)

    v1 = APIRouter(prefix="/v1")  # the token is checked by Gatekeeper, before the body is read
    for module in (scenes, jobs, artifacts, methods, job_kinds, camera_paths):
        v1.include_router(module.router)
    # one pair of routes per registered kind made of a training job
    v1.include_router(work.make_router())
    app.include_router(v1)
    app.include_router(health.router)
    app.include_router(dashboard.router)
    app.include_router(docs.router)

    app.add_middleware(Gatekeeper)  # token, then body size, before any route reads the body
    app.add_middleware(SecurityHeaders)
    app.add_middleware(RequestStats, stats=app.state.http_stats)

    @app.exception_handler(LecoError)
    async def leco_error(request: Request, error: LecoError) -> JSONResponse:
        # A route that needs a field named (a refused body) or a prefix catches its error itself;
        # the rest reach here and are reported by their kind (model/errors.py).
        status = STATUSES[error.kind]
        if status == 500:
            log.error("%s %s: %s", request.method, request.url.path, first_line(error))
        retry = {"Retry-After": str(RETRY_AFTER_S)} if error.kind in RETRY_KINDS else None
        return JSONResponse({"detail": bounded(str(error))}, status, headers=retry)

    @app.exception_handler(OperationalError)
    @app.exception_handler(InterfaceError)
    async def database_unavailable(request: Request, error: Exception) -> JSONResponse:
        # A database restart is not the client's fault nor a bug: 503 with a hint to retry, details
        # in the log.
        log.warning(
            "%s %s: database unavailable: %s", request.method, request.url.path, first_line(error)
        )
        return JSONResponse(
            {"detail": "the database is unavailable right now; retry in a few seconds"},
            503,
            headers={"Retry-After": "2"},
        )

    @app.exception_handler(RequestValidationError)
    async def invalid_request(request: Request, error: RequestValidationError) -> JSONResponse:
        # FastAPI's own shape ({"detail": [{"loc", "msg", "type"}]}) without echoing the input back.
        errors = error.errors()
        detail: list[dict] = [
            {
                "loc": [bounded(part) for part in e["loc"]],
                "msg": bounded(e["msg"]),
                "type": e["type"],
            }
            for e in errors[:MAX_VALIDATION_ERRORS]
        ]
        if len(errors) > MAX_VALIDATION_ERRORS:
            detail.append(
                {
                    "loc": [],
                    "msg": f"and {len(errors) - MAX_VALIDATION_ERRORS:,} more errors",
                    "type": "too_many_errors",
                }
            )
        return JSONResponse({"detail": detail}, 422)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, error: StarletteHTTPException) -> Response:
        if error.status_code in (204, 304):  # no body allowed, as Starlette's own handler does
            return Response(status_code=error.status_code, headers=error.headers)
        return JSONResponse(
            {"detail": bounded(error.detail)}, error.status_code, headers=error.headers
        )

    return app

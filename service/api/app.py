"""The FastAPI application. It refuses to start on a database whose schema is not the one this code needs."""

from __future__ import annotations

import time
from collections import Counter

from fastapi import APIRouter, Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from service.api import artifacts, dashboard, health, jobs, scenes
from service.api.deps import require_token
from service.db import check_schema
from service.settings import Settings


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings.from_env()
    check_schema(settings.db_url)  # raises SchemaError naming the command to run
    app = FastAPI(title="LeCO-NeRF Service", version="1",
                  description="Register scenes, submit LeCO-NeRF / Switch-NeRF / occupancy-grid training jobs, "
                              "follow their metrics, download their artifacts.")
    app.state.settings = settings
    app.state.http_stats = {"count": Counter(), "seconds": 0.0, "started": time.monotonic()}

    v1 = APIRouter(prefix="/v1", dependencies=[Depends(require_token)])
    for module in (scenes, jobs, artifacts):
        v1.include_router(module.router)
    app.include_router(v1)
    app.include_router(health.router)
    app.include_router(dashboard.router)

    @app.middleware("http")
    async def count_requests(request: Request, call_next):
        started = time.perf_counter()
        response = await call_next(request)
        route = request.scope.get("route")
        key = (request.method, getattr(route, "path", "unmatched"), str(response.status_code))
        stats = app.state.http_stats
        stats["count"][key] += 1
        stats["seconds"] += time.perf_counter() - started
        return response

    @app.exception_handler(RequestValidationError)
    async def invalid_request(request: Request, error: RequestValidationError):
        # FastAPI's own shape ({"detail": [{"loc", "msg", "type"}]}) without echoing the input back.
        detail = [{"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]} for e in error.errors()]
        return JSONResponse({"detail": detail}, 422)

    return app

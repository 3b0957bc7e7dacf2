"""/healthz (the process answers), /readyz (the database at the right schema, and Ray), /metrics
(Prometheus)."""

from __future__ import annotations

import logging
import time

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse, PlainTextResponse
from sqlalchemy import func, select, text

from service.api.deps import settings_of
from service.db import check_schema, first_line, reading
from service.settings import Settings
from service.tables import JOB_STATES, Artifact, Job

router = APIRouter(tags=["health"])
log = logging.getLogger("leco.api")


@router.get("/healthz")
def healthz() -> dict:
    return {"status": "ok"}


def ray_status(settings: Settings) -> tuple[bool, str]:
    """(up, what to log): the cluster's Ray Jobs API, or the local Ray this process started."""
    if settings.ray_address:
        import os
        import urllib.request

        request = urllib.request.Request(f"{settings.ray_address.rstrip('/')}/api/version")
        # a cluster with token auth refuses the call without it
        if os.environ.get("RAY_AUTH_TOKEN"):
            request.add_header("Authorization", f"Bearer {os.environ['RAY_AUTH_TOKEN']}")
        try:
            with urllib.request.urlopen(request, timeout=2) as answer:
                return answer.status == 200, f"Ray Jobs API answered {answer.status}"
        except OSError as error:
            return False, f"Ray Jobs API unreachable: {error}"
    import ray

    return ray.is_initialized(), "local Ray not started"


@router.get("/readyz")
def readyz(settings: Settings = Depends(settings_of)) -> JSONResponse:
    """Up or down per dependency and nothing more (it used to show the database URL or path);
    why a dependency is down goes to the log. With LECO_BACKEND=local no Ray is needed."""
    checks, ready = {}, True
    try:
        with reading(settings.db_url) as session:
            session.execute(text("SELECT 1"))
        check_schema(settings.db_url)
        checks["database"] = "up"
    except Exception as error:
        ready, checks["database"] = False, "down"
        log.warning("readyz: database down: %s", first_line(error))
    if settings.backend == "local" and not settings.ray_address:
        checks["ray"] = "not used (LECO_BACKEND=local)"
    else:
        up, why = ray_status(settings)
        ready &= up
        checks["ray"] = "up" if up else "down"
        if not up:
            log.warning("readyz: ray down: %s", why)
    return JSONResponse({"ready": ready, "checks": checks}, 200 if ready else 503)


@router.get("/metrics", response_class=PlainTextResponse)
def prometheus(request: Request, settings: Settings = Depends(settings_of)) -> str:
    lines = []
    with reading(settings.db_url) as session:
        counts = dict(session.execute(select(Job.state, func.count()).group_by(Job.state)).all())
        artifacts, size = session.execute(
            select(func.count(), func.coalesce(func.sum(Artifact.size), 0))
        ).one()
    lines += ["# HELP leco_jobs Jobs by state.", "# TYPE leco_jobs gauge"]
    lines += [f'leco_jobs{{state="{s}"}} {counts.get(s, 0)}' for s in JOB_STATES]
    lines += [
        "# HELP leco_artifacts Stored artifacts.",
        "# TYPE leco_artifacts gauge",
        f"leco_artifacts {artifacts}",
        "# HELP leco_artifact_bytes Bytes referenced by artifact rows.",
        "# TYPE leco_artifact_bytes gauge",
        f"leco_artifact_bytes {size}",
    ]
    stats = request.app.state.http_stats
    lines += [
        "# HELP leco_http_requests_total HTTP requests by route and status.",
        "# TYPE leco_http_requests_total counter",
    ]
    lines += [
        f'leco_http_requests_total{{method="{m}",route="{r}",status="{s}"}} {n}'
        for (m, r, s), n in sorted(stats["count"].items())
    ]
    lines += [
        "# HELP leco_http_request_seconds Time spent answering requests.",
        "# TYPE leco_http_request_seconds summary",
        f"leco_http_request_seconds_sum {stats['seconds']:.6f}",
        f"leco_http_request_seconds_count {sum(stats['count'].values())}",
        "# HELP leco_poll_cache_total Polled job views and metrics answered from the poll cache, "
        "or read.",
        "# TYPE leco_poll_cache_total counter",
        f'leco_poll_cache_total{{result="hit"}} {request.app.state.poll_cache.hits}',
        f'leco_poll_cache_total{{result="miss"}} {request.app.state.poll_cache.misses}',
        "# HELP leco_uptime_seconds Seconds since the API started.",
        "# TYPE leco_uptime_seconds gauge",
        f"leco_uptime_seconds {time.monotonic() - stats['started']:.1f}",
    ]
    return "\n".join(lines) + "\n"

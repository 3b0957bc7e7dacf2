"""Work on a finished training job: jobs of every kind made of one (renders, exports:
service/jobs/kinds.py), each kind with a collection under the job to submit and list them, queued
and run by the dispatchers like training; and single views, rendered to PNG by the view pool's
processes with a concurrency limit and a small cache."""

from __future__ import annotations

import hashlib
import json
from collections import OrderedDict
from threading import Lock

from fastapi import APIRouter, Body, HTTPException, Query, Request
from fastapi.encoders import jsonable_encoder
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from model.memory_estimate import describe
from service.api.deps import RowId, SettingsDep, not_found, poll_cache_of
from service.api.feasibility import largest_image_pixels
from service.api.jobs import job_out
from service.api.schemas import JobList, JobOut
from service.db import reading, transaction
from service.jobs.kinds import (
    KINDS,
    JobKind,
    Memory,
    Parent,
    Refused,
    check_appearance,
    get_kind,
    view_memory,
)
from service.jobs.submit import submit
from service.settings import Settings
from service.tables import Job, Scene
from service.view_worker import render_view
from service.workpool import Busy
from workers.config import TrainConfig
from workers.render.schemas import ViewRequest

VIEW_CACHE = 64  # PNGs kept per API process, by (job, request)
VIEW_RETRY_AFTER_S = 1


def refuse(field: list, msg: str) -> HTTPException:
    return HTTPException(422, [{"loc": field, "type": "value_error", "msg": msg}])


def finished_training_job(session: Session, job_id: int, lock: bool = False) -> Job:
    """The job a render, export or view is made of: it must exist (404), be of a kind that trains
    networks and have succeeded (422 naming `job_id`). `lock`: its row is locked until the
    transaction ends, so a delete of it waits for a submit (and sees the new child) or goes first
    (and the submit finds no job)."""
    job = session.get(Job, job_id, with_for_update=lock)
    if job is None:
        raise not_found("job", job_id)
    if job.kind not in KINDS or not get_kind(job.kind).trains:
        raise refuse(
            ["path", "job_id"],
            f"job {job_id} is a {job.kind} job: renders, exports and views are made of training "
            "jobs",
        )
    if job.state != "succeeded":
        raise refuse(
            ["path", "job_id"],
            f"job {job_id} is {job.state}: renders, exports and views need a training job that "
            "succeeded",
        )
    return job


def parent_info(session: Session, job: Job) -> Parent:
    info = session.scalar(select(Scene.info).where(Scene.id == job.scene_id)) or {}
    splits = info.get("splits", {})  # a point cloud is made of the training and validation views
    images = int(splits.get("train", {}).get("images") or info.get("cameras") or 0)
    views = sum(int(splits.get(n, {}).get("images", 0)) for n in ("train", "val")) or 1
    try:
        config: TrainConfig | None = TrainConfig.model_validate(job.config)
    except ValueError:  # a job stored under an older schema: its memory is not estimated
        config = None
    downscale = config.downscale if config is not None else None
    largest = max(
        (largest_image_pixels(info, name, downscale) or 0 for name in ("train", "val")), default=0
    )
    return Parent(job.id, job.method, images, views, config, largest)


def check_memory(memory: Memory | None, settings: Settings, job_id: int) -> None:
    """422 when the job's estimated peak exceeds the memory a job gets here."""
    if memory is None:
        return
    need, slot = memory.estimate["total"], settings.slot_memory_mb * 2**20
    if need > slot:
        mib = lambda b: f"{b / 2**20:,.0f} MiB"
        raise refuse(
            ["body", memory.field],
            f"a job made of job {job_id} this way needs about {mib(need)} and a job here gets "
            f"{mib(slot)}: {describe(memory.estimate)}",
        )


def submit_child(
    request: Request, settings: Settings, job_id: int, kind: JobKind, cfg: BaseModel
) -> JSONResponse:
    with transaction(settings.db_url) as session:
        parent = finished_training_job(session, job_id, lock=True)
        info = parent_info(session, parent)
        try:
            kind.check(cfg, info)
        except Refused as refused:
            raise refuse(["body", refused.field], str(refused)) from None
        check_memory(kind.memory(cfg, info), settings, job_id)
        job = submit(session, kind, parent.scene_id, cfg, parent, info)
        session.flush()
        payload = jsonable_encoder(job_out(session, job))
    poll_cache_of(request).forget(payload["id"])
    return JSONResponse(payload, 201)


def children(settings: Settings, job_id: int, kind: str, limit: int, offset: int) -> JobList:
    with reading(settings.db_url) as session:
        if session.get(Job, job_id) is None:
            raise not_found("job", job_id)
        query = select(Job).where(Job.parent_id == job_id, Job.kind == kind)
        total = session.scalar(select(func.count()).select_from(query.subquery())) or 0
        rows = session.scalars(query.order_by(Job.id.desc()).limit(limit).offset(offset)).all()
        items = [job_out(session, j) for j in rows]
    return JobList(
        items=items,
        total=total,
        limit=limit,
        offset=offset,
        next_offset=offset + limit if offset + limit < total else None,
    )


def add_kind_routes(router: APIRouter, kind: JobKind) -> None:
    """POST and GET /jobs/{job_id}/<kind>s: submit a job of `kind` made of a finished training job,
    list them."""
    title = kind.name.title().replace("-", "").replace("_", "")

    def submit_route(
        job_id: RowId, request: Request, settings: SettingsDep, body: BaseModel = Body()
    ) -> JSONResponse:
        return submit_child(request, settings, job_id, kind, body)

    def list_route(
        job_id: RowId,
        settings: SettingsDep,
        limit: int = Query(50, ge=1, le=200),
        offset: int = Query(0, ge=0, le=2**31 - 1),
    ) -> JobList:
        return children(settings, job_id, kind.name, limit, offset)

    # the kind's own schema, in the OpenAPI document too
    submit_route.__annotations__["body"] = kind.config
    router.add_api_route(
        f"/{{job_id}}/{kind.route}",
        submit_route,
        methods=["POST"],
        status_code=201,
        response_model=JobOut,
        operation_id=f"submit{title}",
        description=kind.description,
        responses={422: {"description": kind.refusals}},
    )
    router.add_api_route(
        f"/{{job_id}}/{kind.route}",
        list_route,
        methods=["GET"],
        response_model=JobList,
        operation_id=f"list{title}s",
    )


def make_router() -> APIRouter:
    """The routes of every registered kind made of a training job, and the view route (made when the
    app is, so a kind registered before then has its routes)."""
    router = APIRouter(prefix="/jobs", tags=["renders"])
    for kind in KINDS.values():
        if kind.route is not None:
            add_kind_routes(router, kind)
    router.add_api_route(
        "/{job_id}/view",
        view,
        methods=["POST"],
        operation_id="renderView",
        response_class=Response,
        responses=VIEW_RESPONSES,
    )
    return router


class ViewCache:
    def __init__(self, size: int):
        self.size, self.items, self.lock = size, OrderedDict[str, tuple[bytes, float]](), Lock()

    def get(self, key: str) -> tuple[bytes, float] | None:
        with self.lock:
            if key in self.items:
                self.items.move_to_end(key)
                return self.items[key]
        return None

    def put(self, key: str, value: tuple[bytes, float]) -> None:
        with self.lock:
            self.items[key] = value
            while len(self.items) > self.size:
                self.items.popitem(last=False)


VIEW_RESPONSES: dict[int | str, dict] = {
    200: {
        "content": {"image/png": {}},
        "description": "the camera's view (X-Render-Seconds: the render's time)",
    },
    422: {
        "description": "the job has not succeeded; a camera that is not a rotation; a preview too "
        "large (over 640x480, or over the memory a job gets here)"
    },
    429: {"description": "the view renderers are busy: retry after Retry-After seconds"},
}


def view(job_id: RowId, body: ViewRequest, request: Request, settings: SettingsDep) -> Response:
    """One camera of a finished training job rendered to PNG (a preview: at most 640x480, and
    within the memory a job gets, estimated as a render's frame is), by the method's own sampler, in
    one of the view pool's processes; repeated requests are answered from a small cache."""
    with reading(settings.db_url) as session:
        job = finished_training_job(session, job_id)
        parent = parent_info(session, job)
        try:
            check_appearance(body.appearance, parent.images)
        except Refused as refused:
            raise refuse(["body", refused.field], str(refused)) from None
    check_memory(view_memory(body, parent), settings, job_id)
    key = hashlib.sha256(
        json.dumps([job_id, body.model_dump(mode="json")], sort_keys=True).encode()
    ).hexdigest()
    cache: ViewCache = request.app.state.view_cache
    hit = cache.get(key)
    if hit is None:
        pool = request.app.state.view_pool
        try:
            pool.admit()
        except Busy:
            raise HTTPException(
                429,
                f"the view renderers are busy ({pool.workers} rendering, {pool.queue} waiting); "
                f"retry in {VIEW_RETRY_AFTER_S} s",
                headers={"Retry-After": str(VIEW_RETRY_AFTER_S)},
            ) from None
        try:
            with pool.running():
                hit = pool.call(render_view, settings, job_id, body.model_dump(mode="json"))
        finally:
            pool.release()
        cache.put(key, hit)
    png, seconds = hit
    return Response(
        png,
        media_type="image/png",
        headers={"X-Render-Seconds": f"{seconds:.4f}", "Cache-Control": "private, max-age=3600"},
    )

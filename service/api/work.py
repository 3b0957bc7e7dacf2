"""Work on a finished training job: render jobs (a video along a camera path) and export jobs
(geometry in the dataset's frame), queued and run by the dispatchers like training; and single views,
rendered to PNG by the view pool's processes with a concurrency limit and a small cache."""

from __future__ import annotations

import hashlib
import json
from collections import OrderedDict
from threading import Lock

from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.encoders import jsonable_encoder
from fastapi.responses import JSONResponse, Response
from sqlalchemy import func, select

from model.methods import get_method
from service import queue
from service.api.deps import RowId, not_found, poll_cache_of
from service.api.jobs import job_out
from service.api.schemas import JobList, JobOut
from service.db import reading, transaction
from service.derived import steps_of
from service.settings import Settings
from service.tables import Job, Scene
from service.view_worker import render_view
from service.workpool import Busy
from workers.render_config import ExportConfig, RenderConfig, ViewRequest

router = APIRouter(prefix="/jobs", tags=["renders"])
VIEW_CACHE = 64  # PNGs kept per API process, by (job, request)
VIEW_RETRY_AFTER_S = 1


def refuse(field: list, msg: str) -> HTTPException:
    return HTTPException(422, [{"loc": field, "type": "value_error", "msg": msg}])


def finished_training_job(session, job_id: int, lock: bool = False) -> Job:
    """The job a render, export or view is made of: it must exist (404), be a training job and have succeeded
    (422 naming `job_id`). `lock`: its row is locked until the transaction ends, so a delete of it waits for a
    submit (and sees the new child) or goes first (and the submit finds no job)."""
    job = session.get(Job, job_id, with_for_update=lock)
    if job is None:
        raise not_found("job", job_id)
    if job.kind != "train":
        raise refuse(["path", "job_id"], f"job {job_id} is a {job.kind} job: renders, exports and views are made of "
                                         "training jobs")
    if job.state != "succeeded":
        raise refuse(["path", "job_id"], f"job {job_id} is {job.state}: renders, exports and views need a training "
                                         "job that succeeded")
    return job


def training_images(session, job: Job) -> int:
    info = session.scalar(select(Scene.info).where(Scene.id == job.scene_id)) or {}
    return int(info.get("splits", {}).get("train", {}).get("images") or info.get("cameras") or 0)


def check_appearance(appearance, images: int, field: list) -> None:
    if appearance != "mean" and int(appearance) >= images:
        raise refuse(field, f"training image {appearance} does not exist: the job's scene has {images} training "
                            f"images (0 to {images - 1}), or use 'mean'")


def submit(request: Request, job_id: int, kind: str, cfg: RenderConfig | ExportConfig) -> JSONResponse:
    settings: Settings = request.app.state.settings
    with transaction(settings.db_url) as session:
        parent = finished_training_job(session, job_id, lock=True)
        images = training_images(session, parent)
        if isinstance(cfg, RenderConfig):
            check_appearance(cfg.appearance, images, ["body", "appearance"])
        elif cfg.what == "occupancy" and not get_method(parent.method).has_occupancy:
            raise refuse(["body", "what"], f"job {job_id}'s method {parent.method!r} learns no occupancy: there is "
                                           "none to export (pointcloud and cameras are)")
        info = session.scalar(select(Scene.info).where(Scene.id == parent.scene_id)) or {}
        splits = info.get("splits", {})  # a point cloud is made of the training and validation views
        phase, steps = steps_of(cfg, sum(int(splits.get(n, {}).get("images", 0)) for n in ("train", "val")) or 1)
        job = queue.submit_work(session, parent, kind, cfg.model_dump(mode="json"), phase, steps)
        session.flush()
        payload = jsonable_encoder(job_out(session, job))
    poll_cache_of(request).forget(payload["id"])
    return JSONResponse(payload, 201)


def children(request: Request, job_id: int, kind: str, limit: int, offset: int) -> JobList:
    settings: Settings = request.app.state.settings
    with reading(settings.db_url) as session:
        if session.get(Job, job_id) is None:
            raise not_found("job", job_id)
        query = select(Job).where(Job.parent_id == job_id, Job.kind == kind)
        total = session.scalar(select(func.count()).select_from(query.subquery())) or 0
        rows = session.scalars(query.order_by(Job.id.desc()).limit(limit).offset(offset)).all()
        items = [job_out(session, j) for j in rows]
    return JobList(items=items, total=total, limit=limit, offset=offset,
                   next_offset=offset + limit if offset + limit < total else None)


@router.post("/{job_id}/renders", status_code=201, response_model=JobOut, operation_id="submitRender", responses={
    422: {"description": "the job has not succeeded or is not a training job; a bad path, size or frame count"}})
def submit_render(job_id: RowId, body: RenderConfig, request: Request) -> JSONResponse:
    """A video of a finished training job along a camera path: a render job, queued and run by a dispatcher
    (progress, cancel and artifacts as for any job: `video.mp4`, `video.poster.png`, ...)."""
    return submit(request, job_id, "render", body)


@router.get("/{job_id}/renders", response_model=JobList, operation_id="listRenders")
def list_renders(job_id: RowId, request: Request, limit: int = Query(50, ge=1, le=200),
                 offset: int = Query(0, ge=0, le=2**31 - 1)) -> JobList:
    return children(request, job_id, "render", limit, offset)


@router.post("/{job_id}/exports", status_code=201, response_model=JobOut, operation_id="submitExport", responses={
    422: {"description": "the job has not succeeded or is not a training job; an occupancy its method lacks"}})
def submit_export(job_id: RowId, body: ExportConfig, request: Request) -> JSONResponse:
    """Geometry of a finished training job in the dataset's own frame and units: an export job whose artifacts
    are the file (pointcloud.ply, cameras.json or occupancy.ply), transform.json and export.json."""
    return submit(request, job_id, "export", body)


@router.get("/{job_id}/exports", response_model=JobList, operation_id="listExports")
def list_exports(job_id: RowId, request: Request, limit: int = Query(50, ge=1, le=200),
                 offset: int = Query(0, ge=0, le=2**31 - 1)) -> JobList:
    return children(request, job_id, "export", limit, offset)


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


@router.post("/{job_id}/view", operation_id="renderView", response_class=Response, responses={
    200: {"content": {"image/png": {}}, "description": "the camera's view (X-Render-Seconds: the render's time)"},
    422: {"description": "the job has not succeeded; a camera that is not a rotation; a preview too large"},
    429: {"description": "the view renderers are busy: retry after Retry-After seconds"}})
def view(job_id: RowId, body: ViewRequest, request: Request) -> Response:
    """One camera of a finished training job rendered to PNG (a preview: at most 640x480), by the method's own
    sampler, in one of the view pool's processes; repeated requests are answered from a small cache."""
    settings: Settings = request.app.state.settings
    with reading(settings.db_url) as session:
        job = finished_training_job(session, job_id)
        check_appearance(body.appearance, training_images(session, job), ["body", "appearance"])
    key = hashlib.sha256(json.dumps([job_id, body.model_dump(mode="json")], sort_keys=True).encode()).hexdigest()
    cache: ViewCache = request.app.state.view_cache
    hit = cache.get(key)
    if hit is None:
        pool = request.app.state.view_pool
        try:
            pool.admit()
        except Busy:
            raise HTTPException(429, f"the view renderers are busy ({pool.workers} rendering, {pool.queue} waiting); "
                                     f"retry in {VIEW_RETRY_AFTER_S} s",
                                headers={"Retry-After": str(VIEW_RETRY_AFTER_S)}) from None
        try:
            with pool.running():
                hit = pool.call(render_view, settings, job_id, body.model_dump(mode="json"))
        finally:
            pool.release()
        cache.put(key, hit)
    png, seconds = hit
    return Response(png, media_type="image/png", headers={"X-Render-Seconds": f"{seconds:.4f}",
                                                          "Cache-Control": "private, max-age=3600"})

"""/v1/jobs: submit (with Idempotency-Key), list, show, cancel, delete; per-job metrics."""

from __future__ import annotations

import hashlib
import json
import shutil
from datetime import timedelta

from fastapi import APIRouter, Header, HTTPException, Query, Request
from fastapi.encoders import jsonable_encoder
from fastapi.responses import JSONResponse, Response
from sqlalchemy import case, delete, func, select, true
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from model.memory_estimate import RUNTIME_BYTES, describe, estimate_peak_bytes
from model.scenes.folders import folder_factor
from model.sizes import resident_pixel_bytes
from service import queue
from service.api.deps import MAX_INT, RowId, SettingsDep, not_found, poll_cache_of
from service.api.feasibility import check_feasible, local_gpus, scene_sizes, training_pixels
from service.api.links import (
    cancelled_job_links,
    deleted_job_links,
    job_links,
    links,
    submitted_job_links,
)
from service.api.methods import check_method_filter
from service.api.scenes import find_scene
from service.api.schemas import JobList, JobOut, JobRequest, MetricsOut, PhaseOut, Point, Series
from service.db import reading, transaction
from service.jobs.kinds import KINDS, TRAIN, get_kind
from service.jobs.paths import job_dir_for
from service.jobs.submit import submit as enqueue
from service.settings import Settings
from service.store import ArtifactStore
from service.tables import JOB_STATES, TERMINAL, IdempotencyKey, Job, JobPhase, Metric, utcnow
from workers.config import TrainConfig

router = APIRouter(prefix="/jobs", tags=["jobs"])
# an in-flight key older than this belonged to a request that died
STALE_IN_FLIGHT = timedelta(minutes=5)
# an Idempotency-Key that created a job is answered for this long, then forgotten (a refused
# request keeps no key: submit)
KEY_TTL = timedelta(hours=24)
KEY_HEADER = Header(
    None,
    min_length=1,
    max_length=255,
    pattern=r"^[\x21-\x7e]+$",
    description="1-255 visible ASCII characters, scoped to the bearer token that sends it; the job "
    "it created is answered for 24 hours (a refused request keeps nothing: sent again, it is "
    "checked again)",
)


def job_out(session: Session, job: Job) -> JobOut:
    phases = session.scalars(
        select(JobPhase).where(JobPhase.job_id == job.id).order_by(JobPhase.position)
    ).all()
    metrics: dict[str, dict[str, float]] = {}
    # one index lookup per phase (ix_metrics_job_phase_step), not a scan of the job's rows
    for phase in phases:
        last = (
            select(func.max(Metric.step))
            .where(Metric.job_id == job.id, Metric.phase == phase.name)
            .scalar_subquery()
        )
        rows = session.execute(
            select(Metric.name, Metric.value).where(
                Metric.job_id == job.id, Metric.phase == phase.name, Metric.step == last
            )
        ).all()
        if rows:
            metrics[phase.name] = dict(rows)
    eta = None
    batch = rays_per_step(job)
    if job.state == "running" and job.rays_per_s and batch:
        eta = max(job.total_steps - job.step, 0) * batch / job.rays_per_s
    percent = (
        100.0 if job.state == "succeeded" else round(100.0 * job.step / max(job.total_steps, 1), 2)
    )
    trains = job.kind in KINDS and get_kind(job.kind).trains
    return JobOut(
        id=job.id,
        kind=job.kind,
        trains=trains,
        parent_id=job.parent_id,
        scene_id=job.scene_id,
        state=job.state,
        method=job.method,
        profile=job.profile,
        config=job.config,
        phase=job.phase,
        step=job.step,
        total_steps=job.total_steps,
        percent=percent,
        eta_s=eta,
        rays_per_s=job.rays_per_s,
        attempts=job.attempts,
        cancel_requested=job.cancel_requested,
        error=job.error,
        submitted_at=job.submitted_at,
        started_at=job.started_at,
        finished_at=job.finished_at,
        latest_metrics=metrics,
        phases=[PhaseOut.model_validate(p, from_attributes=True) for p in phases],
    )


def rays_per_step(job: Job) -> int | None:
    """Rays one step of the job renders or trains (its ETA); None where steps differ, for a kind
    no longer registered, or for a config stored under an older schema."""
    if job.kind not in KINDS:
        return None
    kind = get_kind(job.kind)
    try:
        config = kind.config_of(job.config)
    except ValueError:  # e.g. an override `"2"` for an integer, taken before overrides were strict
        return None
    return kind.rays_per_step(config)


def check_resources(
    cfg: TrainConfig,
    settings: Settings,
    num_images: int,
    ray_fraction: float = 1.0,
    train_pixels: int | None = None,
) -> None:
    """Refuse, with 422 naming the fields, a job that cannot run where it would: more workers than
    there are, or a peak memory (model/memory_estimate.py) over the slot's RAM or a GPU's
    memory. `ray_fraction`: the scene's mean_diagonal_fraction (1 for a scene registered before it
    was recorded: the most a march can take); `train_pixels`: its training split's pixels at the
    job's downscale, which a GPU rank keeps on the device up to `pixels_on_device_max_mb` (None:
    not recorded, counted as none)."""
    problems = []

    def problem(field: str, msg: str) -> None:
        problems.append({"loc": ["body", field], "type": "value_error", "msg": msg})

    cluster = settings.ray_address is not None
    if cluster and cfg.workers > settings.cluster_max_workers:
        problem(
            "workers",
            f"{cfg.workers} workers asked for; this cluster gives a job at most "
            f"{settings.cluster_max_workers}",
        )
    if not cluster and cfg.workers > settings.local_cpus:
        problem(
            "workers",
            f"{cfg.workers} workers asked for; this service's local Ray has {settings.local_cpus} "
            "CPUs",
        )
    gpu_memory = None
    # GPUs against the workers: check_feasible (service/api/feasibility.py), before this
    if cfg.use_gpu and not cluster and local_gpus(settings) > 0:
        import torch

        if torch.cuda.is_available():
            gpu_memory = torch.cuda.get_device_properties(0).total_memory
    resident = (
        resident_pixel_bytes(train_pixels, cfg.pixels_on_device_max_mb)
        if cfg.use_gpu and train_pixels
        else 0
    )
    estimate = estimate_peak_bytes(
        cfg.method, cfg.resolved_profile(), num_images, ray_fraction, resident
    )
    per_rank, mib = estimate["total"], lambda b: f"{b / 2**20:,.0f} MiB"
    if gpu_memory is not None and per_rank - RUNTIME_BYTES > gpu_memory:
        problem(
            "overrides",
            f"the job needs about {mib(per_rank - RUNTIME_BYTES)} per GPU and a GPU here has "
            f"{mib(gpu_memory)}: {describe(estimate)}",
        )
    if not cfg.use_gpu:
        # a cluster worker is one rank; locally every rank is here
        ranks = 1 if cluster else cfg.workers
        need, slot = ranks * per_rank, settings.slot_memory_mb * 2**20
        if need > slot:
            problem(
                "overrides",
                f"the job needs about {mib(need)} ({ranks} rank(s) x {mib(per_rank)}) and a job "
                f"here gets {mib(slot)}: {describe(estimate)}",
            )
    if problems:
        raise HTTPException(422, problems)


def check_downscale(cfg: TrainConfig, scene_name: str, factors: list[int] | None) -> None:
    """An LLFF scene serves a downscale only as a multiple of one of its image folders' factors:
    refuse any other at submit time (422) instead of failing in the worker."""
    if cfg.downscale is None or not factors or folder_factor(factors, cfg.downscale) is not None:
        return
    have = ", ".join("images" if f == 1 else f"images_{f}" for f in factors)
    raise HTTPException(
        422,
        [
            {
                "loc": ["body", "downscale"],
                "type": "value_error",
                "msg": f"scene {scene_name!r} is an LLFF capture with {have}: downscale "
                f"{cfg.downscale} must be a multiple of {' or '.join(map(str, factors))}",
            }
        ],
    )


def create_job(
    body: JobRequest, settings: Settings, idempotency_key: str | None = None
) -> tuple[int, dict]:
    cfg = body.train_config()
    with reading(settings.db_url) as session:  # the estimate runs outside the write transaction
        scene = find_scene(session, body.scene)
        info = scene_sizes(scene)  # a generating synthetic scene's from its preset
    name = scene.name if scene is not None else ""
    check_downscale(cfg, name, info.get("image_folder_factors"))
    check_feasible(cfg, settings, name, info)
    rays = (info.get("bounds") or {}).get("rays") or {}
    check_resources(
        cfg,
        settings,
        info.get("cameras") or 1000,
        rays.get("mean_diagonal_fraction", 1.0),
        training_pixels(info, cfg.downscale),
    )
    with transaction(settings.db_url) as session:
        scene = find_scene(session, body.scene)
        if scene is None:
            raise not_found("scene", body.scene)
        if scene.state == "failed":
            raise HTTPException(
                409,
                f"scene {scene.name!r} failed ({scene.error}); it cannot be trained",
            )
        job = enqueue(session, TRAIN, scene.id, cfg)
        session.flush()
        payload = jsonable_encoder(job_out(session, job))
        # the job and the key's answer commit together, or neither does
        if idempotency_key is not None:
            record_answer(session, idempotency_key, 201, payload)
        return 201, payload


def record_answer(session: Session, key: str, status: int, payload: dict) -> None:
    row = session.get(IdempotencyKey, key)
    assert row is not None  # begin_idempotent inserted it
    row.state, row.status_code, row.response = "done", status, payload


@router.post(
    "",
    status_code=201,
    response_model=JobOut,
    operation_id="submitJob",
    responses={
        **links(201, submitted_job_links()),
        409: {"description": "a request with this Idempotency-Key is still in flight"},
        410: {"description": "the job this Idempotency-Key created was deleted"},
        422: {
            "description": "invalid body, an invalid Idempotency-Key, or one used with another body"
        },
    },
)
def submit(
    body: JobRequest,
    request: Request,
    settings: SettingsDep,
    idempotency_key: str | None = KEY_HEADER,
) -> JSONResponse:
    if idempotency_key is None:
        status, payload = create_job_or_error(body, settings)
        return submitted(request, status, payload)
    idempotency_key = stored_key(request.headers.get("authorization", ""), idempotency_key)
    digest = hashlib.sha256(
        json.dumps(body.model_dump(mode="json"), sort_keys=True).encode()
    ).hexdigest()
    replay = begin_idempotent(settings, idempotency_key, digest)
    if replay is not None:
        return replay
    try:
        status, payload = create_job_or_error(body, settings, idempotency_key)
    except BaseException:
        forget_key(settings, idempotency_key)  # an unexpected failure: the client may retry
        raise
    if status != 201:
        # Refused: nothing was written, and the same request sent again is checked again, which
        # answers the same while what it depends on is unchanged. So its key is not kept: the rows
        # grow with the jobs made, not with the rate of refused requests.
        forget_key(settings, idempotency_key)
    return submitted(request, status, payload)


def forget_key(settings: Settings, key: str) -> None:
    with transaction(settings.db_url) as session:
        session.execute(
            delete(IdempotencyKey).where(IdempotencyKey.key == key),
            execution_options={"synchronize_session": False},
        )


def submitted(request: Request, status: int, payload: dict) -> JSONResponse:
    if status == 201:
        # the job lists this process serves now show it
        poll_cache_of(request).forget(payload["id"])
    return JSONResponse(payload, status)


def create_job_or_error(
    body: JobRequest, settings: Settings, idempotency_key: str | None = None
) -> tuple[int, dict]:
    try:
        return create_job(body, settings, idempotency_key)
    except HTTPException as error:
        return error.status_code, {"detail": error.detail}


def stored_key(authorization: str, key: str) -> str:
    """The key as stored: hashed with the bearer token that sent it, so two clients' keys never
    meet (and a key's answer is never shown to another token)."""
    token = authorization.partition(" ")[2].strip()
    return hashlib.sha256(f"{token}\n{key}".encode()).hexdigest()


def begin_idempotent(settings: Settings, key: str, digest: str) -> JSONResponse | None:
    """Records the key as in flight (None: go on), or answers for it: the job it created as it is
    now (410 once deleted), 422 for another body, 409 while the first request is still in flight.
    Keys older than KEY_TTL are forgotten first."""
    try:
        with transaction(settings.db_url) as session:
            session.execute(
                delete(IdempotencyKey).where(IdempotencyKey.created_at < utcnow() - KEY_TTL),
                execution_options={"synchronize_session": False},
            )
            row = session.get(IdempotencyKey, key)
            if (
                row is not None
                and row.state == "in_flight"
                and utcnow() - row.created_at > STALE_IN_FLIGHT
            ):
                session.delete(row)
                session.flush()
                row = None
            if row is None:
                session.add(
                    IdempotencyKey(
                        key=key, request_hash=digest, state="in_flight", created_at=utcnow()
                    )
                )
                return None
    except IntegrityError:  # another request inserted the key between our read and our write
        with reading(settings.db_url) as session:
            row = session.get(IdempotencyKey, key)
    # the request that inserted the key failed and removed it since: a retry goes through
    if row is None:
        return JSONResponse(
            {"detail": "a request with this Idempotency-Key is still in flight; retry later"}, 409
        )
    if row.request_hash != digest:
        return JSONResponse(
            {
                "detail": [
                    {
                        "loc": ["header", "Idempotency-Key"],
                        "type": "value_error",
                        "msg": "this Idempotency-Key was used with a different request body",
                    }
                ]
            },
            422,
        )
    if row.state == "in_flight":
        return JSONResponse(
            {"detail": "a request with this Idempotency-Key is still in flight; retry later"}, 409
        )
    if row.status_code is None:  # record_answer sets it together with state 'done'
        raise RuntimeError(f"Idempotency-Key {key!r} is done but has no stored answer")
    replayed = {"Idempotent-Replayed": "true"}
    # a refusal stored by an earlier version (refusals are no longer kept): gone after KEY_TTL
    if row.status_code != 201 or row.response is None:
        return JSONResponse(row.response, row.status_code, headers=replayed)
    with reading(settings.db_url) as session:  # the job it created, as it is now
        job = session.get(Job, row.response["id"])
        if job is None:
            detail = f"job {row.response['id']}, created by this Idempotency-Key, was deleted"
            return JSONResponse({"detail": detail}, 410, headers=replayed)
        return JSONResponse(jsonable_encoder(job_out(session, job)), 201, headers=replayed)


@router.get(
    "", response_model=JobList, operation_id="listJobs", responses=links(200, job_links("/items/0"))
)
async def list_jobs(
    request: Request,
    settings: SettingsDep,
    state: str | None = Query(None, pattern="^(" + "|".join(JOB_STATES) + ")$"),
    scene: str | None = None,
    method: str | None = Query(None, max_length=64),
    # Checked below (422 naming the kinds); the enum tells clients and the fuzz the built-in ones.
    kind: str | None = Query(None, max_length=64, json_schema_extra={"enum": list(KINDS)}),
    trains: bool | None = Query(None, description="only jobs of kinds that train (or that do not)"),
    limit: int = Query(50, ge=1, le=200),
    offset: int = Query(0, ge=0, le=MAX_INT),
) -> Response:
    # The dashboard's jobs page polls this: served from the poll cache, at most LECO_POLL_CACHE_S
    # old.
    check_method_filter(method)
    check_kind_filter(kind)
    body = await poll_cache_of(request).job_list(
        (state, scene, method, kind, trains, limit, offset),
        lambda: job_list_json(settings, state, scene, method, limit, offset, kind, trains),
    )
    return Response(body, media_type="application/json")


def check_kind_filter(kind: str | None) -> None:
    """A `?kind=` filter must name a registered job kind: 422 naming the choices otherwise."""
    if kind is not None and kind not in KINDS:
        raise HTTPException(
            422,
            [
                {
                    "loc": ["query", "kind"],
                    "type": "value_error",
                    "msg": f"unknown job kind {kind!r}: choose one of {', '.join(KINDS)}",
                }
            ],
        )


def job_list_json(
    settings: Settings,
    state: str | None,
    scene: str | None,
    method: str | None,
    limit: int,
    offset: int,
    kind: str | None = None,
    trains: bool | None = None,
) -> bytes:
    with reading(settings.db_url) as session:
        query = select(Job)
        if kind:
            query = query.where(Job.kind == kind)
        if trains is not None:
            query = query.where(
                Job.kind.in_([k.name for k in KINDS.values() if k.trains == trains])
            )
        if state:
            query = query.where(Job.state == state)
        if method:
            query = query.where(Job.method == method)
        if scene is not None:
            row = find_scene(session, scene)
            query = query.where(Job.scene_id == (row.id if row else -1))
        total = session.scalars(select(func.count()).select_from(query.subquery())).one()
        jobs = session.scalars(query.order_by(Job.id.desc()).limit(limit).offset(offset)).all()
        items = [job_out(session, j) for j in jobs]
    return (
        JobList(
            items=items,
            total=total,
            limit=limit,
            offset=offset,
            next_offset=offset + limit if offset + limit < total else None,
        )
        .model_dump_json()
        .encode()
    )


def get_job(session: Session, job_id: int) -> Job:
    job = session.get(Job, job_id)
    if job is None:
        raise not_found("job", job_id)
    return job


def job_view_json(settings: Settings, job_id: int) -> bytes:
    with reading(settings.db_url) as session:
        return job_out(session, get_job(session, job_id)).model_dump_json().encode()


@router.get("/{job_id}", response_model=JobOut, operation_id="getJob")
async def show_job(job_id: RowId, request: Request, settings: SettingsDep) -> Response:
    # Polled by every open dashboard: served from the poll cache (service/api/poll_cache.py), at
    # most LECO_POLL_CACHE_S old, encoded once for all pollers.
    body = await poll_cache_of(request).job_view(job_id, lambda: job_view_json(settings, job_id))
    return Response(body, media_type="application/json")


@router.post(
    "/{job_id}/cancel",
    response_model=JobOut,
    operation_id="cancelJob",
    responses={**links(200, cancelled_job_links()), 409: {"description": "the job already ended"}},
)
def cancel_job(job_id: RowId, request: Request, settings: SettingsDep) -> Response:
    state = queue.cancel(settings.db_url, job_id)
    poll_cache_of(request).forget(job_id)  # the next poll shows the request
    if state is None:
        raise not_found("job", job_id)
    if state in ("succeeded", "failed"):
        raise HTTPException(409, f"job {job_id} already {state}; there is nothing to cancel")
    return Response(job_view_json(settings, job_id), media_type="application/json")


@router.delete(
    "/{job_id}",
    status_code=204,
    operation_id="deleteJob",
    responses={**links(204, deleted_job_links()), 409: {"description": "the job has not ended"}},
)
def delete_job(job_id: RowId, request: Request, settings: SettingsDep) -> None:
    store = ArtifactStore(settings.db_url, settings.artifacts)
    # One transaction under the job's row lock: a render or export submitted meanwhile (which locks
    # the same row) is either seen here, and refused with the delete, or comes after it and finds no
    # job. Never both.
    with transaction(settings.db_url) as session:
        job = session.get(Job, job_id, with_for_update=True)
        if job is None:
            raise not_found("job", job_id)
        if job.state not in TERMINAL:
            raise HTTPException(
                409, f"job {job_id} is {job.state}: cancel it and wait for it to stop first"
            )
        works = session.execute(
            select(Job.id, Job.kind, Job.state)
            .where(Job.parent_id == job_id)
            # no dispatcher claims one of them meanwhile
            .with_for_update()
        ).all()
        # its renders and exports go with it (the rows by ON DELETE CASCADE)
        for work_id, kind, state in works:
            if state not in TERMINAL:
                raise HTTPException(
                    409,
                    f"job {job_id}'s {kind} job {work_id} is {state}: cancel it and wait for it to "
                    "stop first",
                )
        gone = [w[0] for w in works] + [job_id]
        shas = store.shas_of(session, gone)
        session.execute(
            delete(Job).where(Job.id.in_(gone)), execution_options={"synchronize_session": False}
        )
    # blobs after their rows: a crash in between leaves orphans that collect_orphans removes
    store.collect(shas)
    for ident in gone:
        poll_cache_of(request).forget(ident)
        shutil.rmtree(job_dir_for(settings, ident), ignore_errors=True)


@router.get("/{job_id}/metrics", response_model=MetricsOut, operation_id="getJobMetrics")
async def metrics(
    job_id: RowId,
    request: Request,
    settings: SettingsDep,
    phase: str | None = None,
    name: list[str] | None = Query(None),
    after_step: int = Query(-1, ge=-1, le=MAX_INT),
    max_points: int = Query(1000, ge=1, le=100_000),
) -> Response:
    # Polled with after_step by every open dashboard: served from the poll cache, never older than
    # the job view this process serves (see service/api/poll_cache.py).
    key = (phase, tuple(name or ()), after_step, max_points)
    body = await poll_cache_of(request).metrics(
        job_id,
        key,
        lambda: job_view_json(settings, job_id),
        lambda: metrics_json(settings, job_id, phase, name, after_step, max_points),
    )
    return Response(body, media_type="application/json")


def metrics_json(
    settings: Settings,
    job_id: int,
    phase: str | None,
    name: list[str] | None,
    after_step: int,
    max_points: int,
) -> bytes:
    # Downsampled in SQL: a long job has hundreds of thousands of rows, and only max_points a series
    # leave the database. Row i of a series of n is kept when (i * a) mod (n - 1) < a, a =
    # max_points - 1: the first row at or after each of a + 1 evenly spaced positions, so the first
    # and the last always.
    series = (Metric.phase, Metric.name)
    i = func.row_number().over(partition_by=series, order_by=Metric.step) - 1
    inner = select(
        Metric.phase,
        Metric.name,
        Metric.step,
        Metric.value,
        Metric.wall_time_s,
        i.label("i"),
        func.count().over(partition_by=series).label("n"),
    ).where(Metric.job_id == job_id, Metric.step > after_step)
    if phase:
        inner = inner.where(Metric.phase == phase)
    if name:
        inner = inner.where(Metric.name.in_(name))
    t = inner.subquery()
    a = max_points - 1
    thinned = (t.c.i == t.c.n - 1) if a == 0 else ((t.c.i * a) % (t.c.n - 1) < a)
    keep = case((t.c.n <= max_points, true()), else_=thinned)  # CASE: never a modulo by zero
    with reading(settings.db_url) as session:
        get_job(session, job_id)
        rows = session.execute(
            select(t.c.phase, t.c.name, t.c.step, t.c.value, t.c.wall_time_s, t.c.n)
            .where(keep)
            .order_by(t.c.phase, t.c.name, t.c.step)
        ).all()
    grouped: dict[tuple[str, str], list[Point]] = {}
    totals: dict[tuple[str, str], int] = {}
    for p, n, step, value, wall, total in rows:
        grouped.setdefault((p, n), []).append(Point(step=step, value=value, wall_time_s=wall))
        totals[(p, n)] = total
    return (
        MetricsOut(
            job_id=job_id,
            series=[
                Series(phase=p, name=n, points=points, total_points=totals[(p, n)])
                for (p, n), points in grouped.items()
            ],
        )
        .model_dump_json()
        .encode()
    )

"""/v1/scenes: register a synthetic scene, upload a dataset or photos to pose; list, show,
delete."""

from __future__ import annotations

import json
import tempfile
from contextlib import asynccontextmanager
from pathlib import Path
from typing import AsyncIterator, Callable

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from pydantic import ValidationError
from sqlalchemy import func, select
from sqlalchemy.orm import Session, object_session

from service import scenes as registry
from service.api.deps import MAX_INT, not_found, scene_pool_of, settings_of
from service.api.links import deleted_scene_links, links, scene_links
from service.api.receiving import receive_body
from service.api.schemas import NAME, SceneOut, SyntheticSceneRequest, id_like_name
from service.db import reading, transaction
from service.jobs.kinds import POSES
from service.settings import Settings
from service.tables import Job, Scene
from service.workpool import WorkerLost, WorkPool
from workers.poses.settings import PosesConfig

router = APIRouter(prefix="/scenes", tags=["scenes"])
# an upload's body: the archive's bytes
ARCHIVE_BODY = {
    "required": True,
    "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}},
}


def scene_out(row: Scene) -> SceneOut:
    info = row.info or {}
    session = object_session(row)
    poses_job = None
    if row.source == "photos" and session is not None:
        poses_job = session.scalar(
            select(func.max(Job.id)).where(Job.scene_id == row.id, Job.kind == POSES.name)
        )
    return SceneOut(
        poses_job=poses_job,
        id=row.id,
        name=row.name,
        source=row.source,
        state=row.state,
        format=row.format,
        cameras=info.get("cameras"),
        bounds=info.get("bounds"),
        generator=row.generator,
        error=row.error,
        created_at=row.created_at,
    )


def _created_scene(settings: Settings, scene_id: int) -> SceneOut:
    with reading(settings.db_url) as session:
        row = session.get(Scene, scene_id)
        if row is None:  # another request deleted it since this one created it
            raise not_found("scene", scene_id)
        return scene_out(row)


def find_scene(session: Session, ident: int | str) -> Scene | None:
    if isinstance(ident, int) or (str(ident).isascii() and str(ident).isdigit()):
        # more digits than a 32-bit id has (and past what int() parses at 4,300)
        if len(str(ident)) > 10:
            return None
        number = int(ident)
        return session.get(Scene, number) if 0 < number <= MAX_INT else None
    return session.scalars(select(Scene).where(Scene.name == str(ident))).first()


@router.post(
    "/synthetic",
    status_code=202,
    response_model=SceneOut,
    operation_id="registerSyntheticScene",
    responses=links(202, scene_links()),
    summary="Register a synthetic city; it is generated in the background (state 'generating' -> "
    "'ready')",
)
def create_synthetic(
    body: SyntheticSceneRequest,
    settings: Settings = Depends(settings_of),
    pool: WorkPool = Depends(scene_pool_of),
) -> SceneOut:
    name = body.name or f"{body.preset}-{body.seed}"
    try:
        scene_id = registry.register_synthetic(settings, name, body.preset, body.seed, pool)
    except registry.SceneConflict as error:
        raise HTTPException(409, str(error)) from None
    return _created_scene(settings, scene_id)


@router.post(
    "/upload",
    status_code=201,
    response_model=SceneOut,
    operation_id="uploadScene",
    responses=links(201, scene_links()),
    summary="Upload a dataset archive (tar or zip of a Mega-NeRF, nerfstudio, Blender, LLFF or "
    "COLMAP folder)",
    openapi_extra={"requestBody": ARCHIVE_BODY},
)
async def upload(
    request: Request,
    name: str = Query(..., pattern=NAME),
    settings: Settings = Depends(settings_of),
    pool: WorkPool = Depends(scene_pool_of),
) -> SceneOut:
    if reason := id_like_name(name):
        raise HTTPException(422, reason)
    async with _received(request, settings) as archive:
        with pool.admitted():
            scene_id = await _register(
                settings, pool, lambda: registry.register_upload(settings, name, archive, pool)
            )
    return _created_scene(settings, scene_id)


@asynccontextmanager
async def _received(request: Request, settings: Settings) -> AsyncIterator[Path]:
    """The request's body in a temporary file, removed afterwards. The body comes first, in a
    receiving slot under deadlines (service/api/receiving.py); only then does the caller take a
    place in the scene pool (Busy -> 429), so a slow client holds no place another registration
    could use."""
    declared = request.headers.get("content-length")
    if declared and declared.isdigit() and int(declared) > settings.max_upload_bytes:
        raise HTTPException(
            413, f"upload is {int(declared)} bytes; the limit is {settings.max_upload_bytes}"
        )
    settings.scenes_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=settings.scenes_dir, prefix=".archive-") as tmp:
        with request.app.state.upload_slots.slot(request.client.host if request.client else ""):
            size = await receive_body(
                request.stream(),
                tmp,
                settings.max_upload_bytes,
                settings.upload_idle_s,
                settings.upload_min_bytes_per_s,
            )
        tmp.flush()
        if size == 0:
            raise HTTPException(422, "empty upload: send the archive's bytes as the request body")
        yield Path(tmp.name)


async def _register(settings: Settings, pool: WorkPool, register: Callable[[], int]) -> int:
    """Runs a registration (service/scenes.py) in a running place of the scene pool, off the event
    loop; what the user's upload got wrong is a 422, a taken name a 409."""
    from starlette.concurrency import run_in_threadpool

    def run() -> int:
        with pool.running():
            return register()

    try:
        return await run_in_threadpool(run)
    except registry.SceneConflict as error:
        raise HTTPException(409, str(error)) from None
    except WorkerLost as error:  # killed while reading it: the same archive would be killed again
        raise HTTPException(422, f"archive refused: {error}") from None
    # ArchiveError, SceneError, unreadable images: the user's archive
    except (ValueError, OSError) as error:
        raise HTTPException(
            422, f"archive refused: {error}".replace(str(settings.scenes_dir), "<upload>")
        ) from None


POSES_PARAMETERS = [
    {
        "name": name,
        "in": "query",
        "required": False,
        "description": schema.get("description", ""),
        "schema": {k: v for k, v in schema.items() if k not in ("title", "description")},
    }
    for name, schema in PosesConfig.model_json_schema()["properties"].items()
]


def poses_config_of(request: Request) -> PosesConfig:
    """The poses settings from the query (every field of workers/poses/settings.py's schema but
    `name`): numbers as JSON, words as they are; an unknown parameter or a bad value is a 422
    naming it."""
    values: dict = {}
    for key, text in request.query_params.items():
        if key == "name":
            continue
        if key not in PosesConfig.model_fields:
            raise HTTPException(
                422,
                [
                    {
                        "loc": ["query", key],
                        "type": "extra_forbidden",
                        "msg": f"unknown setting {key!r}: the poses settings are "
                        f"{', '.join(PosesConfig.model_fields)}",
                    }
                ],
            )
        try:
            values[key] = json.loads(text)
        except json.JSONDecodeError:
            values[key] = text
    try:
        return PosesConfig.model_validate(values)
    except ValidationError as error:
        raise HTTPException(
            422,
            [
                {"loc": ["query", *map(str, e["loc"])], "type": e["type"], "msg": e["msg"]}
                for e in error.errors()
            ],
        ) from None


@router.post(
    "/photos",
    status_code=202,
    response_model=SceneOut,
    operation_id="uploadPhotos",
    responses=links(202, scene_links()),
    summary="Upload an archive of photos without poses (tar or zip); a poses job (COLMAP by "
    "pycolmap) finds them, and the scene goes from 'posing' to 'ready'",
    openapi_extra={
        "parameters": POSES_PARAMETERS,
        "requestBody": ARCHIVE_BODY,
    },
)
async def upload_photos(
    request: Request,
    name: str = Query(..., pattern=NAME),
    settings: Settings = Depends(settings_of),
    pool: WorkPool = Depends(scene_pool_of),
) -> SceneOut:
    if reason := id_like_name(name):
        raise HTTPException(422, reason)
    config = poses_config_of(request)
    async with _received(request, settings) as archive:
        with pool.admitted():
            scene_id = await _register(
                settings,
                pool,
                lambda: registry.register_photos(settings, name, archive, config, pool)[0],
            )
    return _created_scene(settings, scene_id)


@router.get(
    "",
    response_model=list[SceneOut],
    operation_id="listScenes",
    responses=links(200, scene_links("/0")),
)
def list_scenes(settings: Settings = Depends(settings_of)) -> list[SceneOut]:
    with reading(settings.db_url) as session:
        return [scene_out(r) for r in session.scalars(select(Scene).order_by(Scene.id))]


@router.get("/{scene}", response_model=SceneOut, operation_id="getScene")
def show_scene(scene: str, settings: Settings = Depends(settings_of)) -> SceneOut:
    with reading(settings.db_url) as session:
        row = find_scene(session, scene)
        if row is None:
            raise not_found("scene", scene)
        return scene_out(row)


@router.delete(
    "/{scene}",
    status_code=204,
    operation_id="deleteScene",
    responses=links(204, deleted_scene_links()),
)
def delete_scene(scene: str, settings: Settings = Depends(settings_of)) -> None:

    with transaction(settings.db_url) as session:
        row = find_scene(session, scene)
        if row is None:
            raise not_found("scene", scene)
        if row.state in ("generating", "posing"):
            raise HTTPException(
                409,
                f"scene {row.name!r} is still {row.state}; delete it when it is ready or failed",
            )
        jobs = session.scalar(select(func.count()).select_from(Job).where(Job.scene_id == row.id))
        if jobs:
            raise HTTPException(
                409, f"scene {row.name!r} is used by {jobs} job(s); delete those jobs first"
            )
        path, scene_id = Path(row.path), row.id
        session.delete(row)
    registry.remove_scene_files(settings, scene_id, path)


@router.get(
    "/{scene}/cameras",
    operation_id="getSceneCameras",
    summary="Camera centres and viewing directions, and the automatic foreground box",
)
def cameras(
    scene: str, settings: Settings = Depends(settings_of), pool: WorkPool = Depends(scene_pool_of)
) -> dict:
    with reading(settings.db_url) as session:
        row = find_scene(session, scene)
        if row is None:
            raise not_found("scene", scene)
        if row.state != "ready":
            raise HTTPException(409, f"scene {row.name!r} is {row.state}")
        scene_id, path = row.id, Path(row.path)
    # written at registration: no decoding here
    if registry.layout_path(settings, scene_id).is_file():
        return registry.read_layout(settings, scene_id, path, pool)
    # a scene registered before layouts were kept: loaded once, bounded
    with pool.admitted(), pool.running():
        try:
            return registry.read_layout(settings, scene_id, path, pool)
        # SceneError: over today's pixel budget, or changed on disk since
        except ValueError as error:
            raise HTTPException(
                422, f"cannot read the scene's cameras: {error}".replace(str(path), "<scene>")
            ) from None

"""/v1/scenes: register a synthetic scene or upload an archive; list, show, delete."""

from __future__ import annotations

import tempfile
from pathlib import Path

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from service import scenes as registry
from service.api.deps import MAX_INT, not_found, scene_pool_of, settings_of
from service.api.links import deleted_scene_links, links, scene_links
from service.api.receiving import receive_body
from service.api.schemas import NAME, SceneOut, SyntheticSceneRequest, id_like_name
from service.db import reading, transaction
from service.settings import Settings
from service.tables import Job, Scene
from service.workpool import WorkerLost, WorkPool

router = APIRouter(prefix="/scenes", tags=["scenes"])


def scene_out(row: Scene) -> SceneOut:
    info = row.info or {}
    return SceneOut(
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
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {
                "application/octet-stream": {"schema": {"type": "string", "format": "binary"}}
            },
        }
    },
)
async def upload(
    request: Request,
    name: str = Query(..., pattern=NAME),
    settings: Settings = Depends(settings_of),
    pool: WorkPool = Depends(scene_pool_of),
) -> SceneOut:
    if reason := id_like_name(name):
        raise HTTPException(422, reason)
    declared = request.headers.get("content-length")
    if declared and declared.isdigit() and int(declared) > settings.max_upload_bytes:
        raise HTTPException(
            413, f"upload is {int(declared)} bytes; the limit is {settings.max_upload_bytes}"
        )
    settings.scenes_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=settings.scenes_dir, prefix=".archive-") as tmp:
        # The body first, in a receiving slot under deadlines (service/api/receiving.py); only then
        # a place in the scene pool (Busy -> 429), so a slow client holds no place another
        # registration could use.
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
        with pool.admitted():
            scene_id = await _register(settings, name, Path(tmp.name), pool)
    return _created_scene(settings, scene_id)


async def _register(settings: Settings, name: str, archive: Path, pool: WorkPool) -> int:
    from starlette.concurrency import run_in_threadpool

    try:
        return await run_in_threadpool(_register_when_running, pool, settings, name, archive)
    except registry.SceneConflict as error:
        raise HTTPException(409, str(error)) from None
    except WorkerLost as error:  # killed while reading it: the same archive would be killed again
        raise HTTPException(422, f"archive refused: {error}") from None
    # ArchiveError, SceneError, unreadable images: the user's archive
    except (ValueError, OSError) as error:
        raise HTTPException(
            422, f"archive refused: {error}".replace(str(settings.scenes_dir), "<upload>")
        ) from None


def _register_when_running(pool: WorkPool, settings: Settings, name: str, archive: Path) -> int:
    with pool.running():
        return registry.register_upload(settings, name, archive, pool)


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
    import shutil

    with transaction(settings.db_url) as session:
        row = find_scene(session, scene)
        if row is None:
            raise not_found("scene", scene)
        if row.state == "generating":
            raise HTTPException(
                409, f"scene {row.name!r} is still being generated; delete it when it is ready"
            )
        jobs = session.scalar(select(func.count()).select_from(Job).where(Job.scene_id == row.id))
        if jobs:
            raise HTTPException(
                409, f"scene {row.name!r} is used by {jobs} job(s); delete those jobs first"
            )
        path, layout = Path(row.path), registry.layout_path(settings, row.id)
        session.delete(row)
    shutil.rmtree(path, ignore_errors=True)
    layout.unlink(missing_ok=True)


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

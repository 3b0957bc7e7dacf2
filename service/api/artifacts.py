"""/v1/jobs/{id}/artifacts and /v1/artifacts/{id}: list, and download with content type, size,
sha256 ETag and HTTP Range. The bytes are verified against their sha256 before they are served."""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from fastapi.responses import FileResponse, Response
from sqlalchemy import select

from service.api.conditional import none_match_fails
from service.api.deps import RowId, not_found, settings_of
from service.api.jobs import get_job
from service.api.links import artifact_links, links
from service.api.schemas import ArtifactOut
from service.db import reading
from service.settings import Settings
from service.store import ArtifactStore, CorruptArtifact, describe
from service.tables import ARTIFACT_KINDS, Artifact

router = APIRouter(tags=["artifacts"])


def artifact_out(meta: dict) -> ArtifactOut:
    return ArtifactOut(**meta, url=f"/v1/artifacts/{meta['id']}/download")


@router.get(
    "/jobs/{job_id}/artifacts",
    response_model=list[ArtifactOut],
    operation_id="listJobArtifacts",
    responses=links(200, artifact_links("/0")),
)
def list_artifacts(
    job_id: RowId,
    settings: Settings = Depends(settings_of),
    # Checked below (422 naming the kinds); the enum tells clients and the fuzz the choices.
    kind: str | None = Query(None, json_schema_extra={"enum": list(ARTIFACT_KINDS)}),
) -> list[ArtifactOut]:
    if kind is not None and kind not in ARTIFACT_KINDS:
        raise HTTPException(
            422,
            [
                {
                    "loc": ["query", "kind"],
                    "type": "value_error",
                    "msg": f"unknown kind {kind!r}: one of {', '.join(ARTIFACT_KINDS)}",
                }
            ],
        )
    with reading(settings.db_url) as session:
        get_job(session, job_id)
        query = select(Artifact).where(Artifact.job_id == job_id)
        if kind:
            query = query.where(Artifact.kind == kind)
        return [artifact_out(describe(a)) for a in session.scalars(query.order_by(Artifact.id))]


def find_artifact(settings: Settings, artifact_id: int) -> dict:
    with reading(settings.db_url) as session:
        row = session.get(Artifact, artifact_id)
        if row is None:
            raise not_found("artifact", artifact_id)
        return describe(row)


@router.get(
    "/artifacts/{artifact_id}",
    response_model=ArtifactOut,
    operation_id="getArtifact",
    responses=links(200, artifact_links()),
)
def show_artifact(artifact_id: RowId, settings: Settings = Depends(settings_of)) -> ArtifactOut:
    return artifact_out(find_artifact(settings, artifact_id))


@router.head("/artifacts/{artifact_id}/download", include_in_schema=False)
@router.get(
    "/artifacts/{artifact_id}/download",
    operation_id="downloadArtifact",
    responses={
        206: {"description": "the requested byte range"},
        304: {"description": "ETag matched"},
        416: {"description": "range not satisfiable"},
        500: {"description": "the stored bytes failed their sha256 check"},
    },
)
def download(
    artifact_id: RowId, request: Request, settings: Settings = Depends(settings_of)
) -> Response:
    meta = find_artifact(settings, artifact_id)
    etag = f'"{meta["sha256"]}"'
    if none_match_fails(request.headers.get("if-none-match"), etag):
        return Response(status_code=304, headers={"ETag": etag})
    try:
        path = ArtifactStore(settings.db_url, settings.artifacts).verified_path(meta)
    except CorruptArtifact as error:
        raise HTTPException(500, f"integrity check failed: {error}") from None
    filename = meta["name"].rsplit("/", 1)[-1]
    return FileResponse(
        path,
        media_type=meta["content_type"],
        filename=filename,
        headers={"ETag": etag, "X-Checksum-SHA256": meta["sha256"]},
    )

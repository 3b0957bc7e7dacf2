"""GET /v1/camera-paths: the camera-path registry (workers/camera_paths) as clients and the
dashboard see it: each kind's tag, whether it is generated from the scene (a menu entry) or brings
its own cameras, and its fields' JSON schema."""

from __future__ import annotations

import sys

from fastapi import APIRouter
from pydantic import BaseModel, Field

from workers.render.camera_paths.registry import PATH_KINDS

router = APIRouter(prefix="/camera-paths", tags=["renders"])


class PathKindOut(BaseModel):
    kind: str
    generated: bool = Field(
        description="made from the scene and its options alone; else the path brings cameras"
    )
    description: str
    schema_: dict = Field(alias="schema", description="the JSON schema of a `path` of this kind")


class PathKindList(BaseModel):
    items: list[PathKindOut]


def description_of(kind: type) -> str:
    """The kind's docstring, else its file's first paragraph."""
    text = kind.__doc__ or sys.modules[kind.__module__].__doc__ or ""
    return " ".join(text.strip().split("\n\n")[0].split())


@router.get(
    "", response_model=PathKindList, response_model_by_alias=True, operation_id="listCameraPaths"
)
def list_camera_paths() -> PathKindList:
    return PathKindList(
        items=[
            PathKindOut(
                kind=name,
                generated=kind.generated,
                schema=kind.model_json_schema(),
                description=description_of(kind),
            )
            for name, kind in PATH_KINDS.items()
        ]
    )

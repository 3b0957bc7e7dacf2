"""Every camera-path kind a render takes, by its `kind` tag: the render schema
(workers/render/schemas.py), the CLI's `--path` and the dashboard's path menu (GET /v1/camera-paths)
read this table. Adding a kind is a file in this package (a PathKind that builds its path) and one
line here."""

from __future__ import annotations

from typing import Annotated, Any, Callable, Union

from pydantic import Field

from workers.render.camera_paths.base import PathKind
from workers.render.camera_paths.cameras import CamerasPath
from workers.render.camera_paths.flyover import FlyoverPath
from workers.render.camera_paths.nerfstudio import NerfstudioPath
from workers.render.camera_paths.orbit import OrbitPath
from workers.render.camera_paths.spiral import SpiralPath

PATH_KINDS: dict[str, type[PathKind]] = {}
# schemas whose `path` field follows the table (RenderConfig)
_listeners: list[Callable[[], None]] = []


def tag(kind: type[PathKind]) -> str:
    return str(kind.model_fields["kind"].default)


def register_path(kind: type[PathKind]) -> type[PathKind]:
    known = PATH_KINDS.get(tag(kind))
    if known is not None and known is not kind:
        raise ValueError(
            f"camera-path kind {tag(kind)!r} is already registered by {known.__qualname__}"
        )
    PATH_KINDS[tag(kind)] = kind
    changed()
    return kind


def unregister_path(name: str) -> None:
    PATH_KINDS.pop(name)
    changed()


def changed() -> None:
    for listener in _listeners:
        listener()


def on_change(listener: Callable[[], None]) -> None:
    _listeners.append(listener)


def path_type() -> Any:  # a type built at run time, which no static type describes
    """The `path` field's type: any registered kind, told apart by its `kind` tag."""
    return Annotated[Union[tuple(PATH_KINDS.values())], Field(discriminator="kind")]


def generated() -> list[str]:
    return [name for name, kind in PATH_KINDS.items() if kind.generated]


for _kind in (OrbitPath, FlyoverPath, SpiralPath, CamerasPath, NerfstudioPath):
    register_path(_kind)

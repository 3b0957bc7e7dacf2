"""JSON camera files (Blender, nerfstudio): reading with messages that name the file and the
field."""

from __future__ import annotations

import json
from pathlib import Path

import torch
from torch import Tensor

from model.scenes import values
from model.scenes.errors import SceneError
from model.scenes.limits import MAX_JSON_BYTES, check_file_size
from model.scenes.source import check_pose


def read_json(path: Path) -> dict:
    check_file_size(path, MAX_JSON_BYTES, "a JSON camera file")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(path, f"malformed JSON ({exc})") from None
    except OSError as exc:
        raise SceneError(path, f"cannot read file ({exc.strerror})") from None
    if not isinstance(data, dict):
        raise SceneError(path, "must hold a JSON object")
    return data


def field(path: Path, obj: dict, key: str, where: str = "") -> object:
    if key not in obj:
        raise SceneError(path, f"missing field '{key}'{where}")
    return obj[key]


def number(path: Path, obj: dict, key: str, where: str = "", default: float | None = None) -> float:
    """A numeric field (`default` when absent, if given): finite and within the coordinate bound."""
    raw = obj.get(key, default) if default is not None else field(path, obj, key, where)
    return values.number(path, raw, f"field '{key}'{where}")


def frames(path: Path, data: dict) -> list[dict]:
    items = field(path, data, "frames")
    if not isinstance(items, list) or not all(isinstance(f, dict) for f in items):
        raise SceneError(path, "'frames' must be a list of objects")
    return items


def opengl_pose(path: Path, frame: dict, where: str) -> Tensor:
    """A frame's 4x4 (or 3x4) OpenGL camera-to-world matrix, validated, as 3x4 float64."""
    raw = field(path, frame, "transform_matrix", where)
    try:
        matrix = torch.tensor(raw, dtype=torch.float64)
    except (TypeError, ValueError):
        raise SceneError(
            path, f"'transform_matrix'{where} must be a 4x4 array of numbers"
        ) from None
    if matrix.shape not in ((4, 4), (3, 4)):
        raise SceneError(
            path, f"'transform_matrix'{where} must be 4x4, got shape {tuple(matrix.shape)}"
        )
    check_pose(path, matrix[:3], where)
    return matrix[:3]

"""Scenes: one representation for photographed and generated data (see docs/SCENES.md).

The names below load on first use, so a torch-free part of this package (scenes/folders.py,
errors.py) can be imported without PyTorch (the API process does)."""

from importlib import import_module
from typing import Any

_HOMES = {
    "Cameras": "cameras",
    "pixel_rays": "cameras",
    "SceneError": "errors",
    "FORMATS": "formats",
    "detect_format": "formats",
    "load_scene": "load",
    "PixelTable": "rays",
    "RayBatch": "rays",
    "RaySampler": "rays",
    "shard": "rays",
    "Bounds": "scene",
    "Normalization": "scene",
    "GroundTruthOccupancy": "scene",
    "Scene": "scene",
    "Views": "scene",
}

__all__ = sorted(_HOMES)


def __getattr__(name: str) -> Any:
    if name not in _HOMES:
        raise AttributeError(f"module 'model.scenes' has no attribute {name!r}")
    return getattr(import_module(f"model.scenes.{_HOMES[name]}"), name)

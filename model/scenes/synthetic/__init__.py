"""Procedural synthetic scenes (a city, a village) with exact ground truth, written in the Mega-NeRF
format (+ gt/).

The names below load on first use, so the presets (presets.py, plain data) can be imported without
PyTorch (the API process reads a generating scene's image sizes from them). The ray caster is
imported from its module (`model.scenes.synthetic.raycast`): a lazy name equal to a submodule's
would be shadowed by the submodule once anything imports it."""

from importlib import import_module
from typing import Any

_HOMES = {
    "CityGeometry": "geometry",
    "LAYOUTS": "layouts",
    "build_city": "layouts",
    "PRESETS": "presets",
    "CityPreset": "presets",
    "get_preset": "presets",
    "generate": "writer",
}

__all__ = sorted(_HOMES)


def __getattr__(name: str) -> Any:
    if name not in _HOMES:
        raise AttributeError(f"module 'model.scenes.synthetic' has no attribute {name!r}")
    return getattr(import_module(f"model.scenes.synthetic.{_HOMES[name]}"), name)

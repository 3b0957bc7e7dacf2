"""Procedural synthetic scenes (a city, a village) with exact ground truth, written in the Mega-NeRF
format (+ gt/)."""

from model.scenes.synthetic.geometry import CityGeometry
from model.scenes.synthetic.layouts import LAYOUTS, build_city
from model.scenes.synthetic.presets import PRESETS, CityPreset, get_preset
from model.scenes.synthetic.raycast import raycast
from model.scenes.synthetic.writer import generate

__all__ = [
    "LAYOUTS",
    "PRESETS",
    "CityGeometry",
    "CityPreset",
    "build_city",
    "generate",
    "get_preset",
    "raycast",
]

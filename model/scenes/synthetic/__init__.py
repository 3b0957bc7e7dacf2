"""A procedural synthetic city with exact ground truth, written in the Mega-NeRF format (+ gt/)."""

from model.scenes.synthetic.city import CityGeometry, build_city
from model.scenes.synthetic.presets import PRESETS, CityPreset, get_preset
from model.scenes.synthetic.raycast import raycast
from model.scenes.synthetic.writer import generate

__all__ = [
    "PRESETS",
    "CityGeometry",
    "CityPreset",
    "build_city",
    "generate",
    "get_preset",
    "raycast",
]

"""Scenes: one representation for photographed and generated data (see docs/SCENES.md)."""

from model.scenes.cameras import Cameras, pixel_rays
from model.scenes.errors import SceneError
from model.scenes.formats import FORMATS, detect_format
from model.scenes.load import load_scene
from model.scenes.rays import PixelTable, RayBatch, RaySampler, shard
from model.scenes.scene import Bounds, Normalization, OccupancyGrid, Scene, Views

__all__ = [
    "FORMATS", "Bounds", "Cameras", "Normalization", "OccupancyGrid", "PixelTable", "RayBatch", "RaySampler",
    "Scene", "SceneError", "Views", "detect_format", "load_scene", "pixel_rays", "shard",
]

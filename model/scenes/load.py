"""`load_scene`: any supported folder -> the normalised Scene. Read-only: nothing is written near
the data."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from model.scenes.build import build_scene
from model.scenes.errors import SceneError
from model.scenes.formats import detect_format
from model.scenes.formats.blender import load_blender
from model.scenes.formats.colmap import load_colmap
from model.scenes.formats.llff import load_llff
from model.scenes.formats.meganerf import load_meganerf
from model.scenes.formats.nerfstudio import load_nerfstudio
from model.scenes.scene import Scene
from model.scenes.source import SourceScene

Background = tuple[float, float, float]

# format -> its reader, called with (folder, downscale or None, background). Only LLFF reads None
# (its smallest images_N folder); every other format reads it as 1.
READERS: dict[str, Callable[[Path, int | None, Background], SourceScene]] = {
    "meganerf": lambda root, downscale, _: load_meganerf(root, downscale or 1),
    "blender": lambda root, downscale, background: load_blender(root, downscale or 1, background),
    "nerfstudio": lambda root, downscale, _: load_nerfstudio(root, downscale or 1),
    "llff": lambda root, downscale, _: load_llff(root, downscale),
    "colmap": lambda root, downscale, _: load_colmap(root, downscale or 1),
}


def load_scene(
    path: str | Path,
    *,
    downscale: int | None = None,
    background: Background = (1.0, 1.0, 1.0),
) -> Scene:
    """Load a scene folder of any supported format.

    downscale: integer factor applied to images and intrinsics (default 1; for LLFF the smallest
    images_N present). background: RGB in [0, 1] that RGBA images (Blender) are composited on.
    """
    root = Path(path)
    if downscale is not None and (not isinstance(downscale, int) or downscale < 1):
        raise SceneError(root, f"downscale must be a positive integer, got {downscale!r}")
    return build_scene(READERS[detect_format(root)](root, downscale, background))

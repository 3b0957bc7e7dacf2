"""`load_scene`: any supported folder -> the normalised Scene. Read-only: nothing is written near
the data."""

from __future__ import annotations

from pathlib import Path

from model.scenes.build import build_scene
from model.scenes.errors import SceneError
from model.scenes.formats import detect_format
from model.scenes.formats.blender import load_blender
from model.scenes.formats.llff import load_llff
from model.scenes.formats.meganerf import load_meganerf
from model.scenes.formats.nerfstudio import load_nerfstudio
from model.scenes.scene import Scene


def load_scene(
    path: str | Path,
    *,
    downscale: int | None = None,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
) -> Scene:
    """Load a scene folder of any supported format.

    downscale: integer factor applied to images and intrinsics (default 1; for LLFF the smallest
    images_N present). background: RGB in [0, 1] that RGBA images (Blender) are composited on.
    """
    root = Path(path)
    if downscale is not None and (not isinstance(downscale, int) or downscale < 1):
        raise SceneError(root, f"downscale must be a positive integer, got {downscale!r}")
    fmt = detect_format(root)
    if fmt == "llff":
        source = load_llff(root, downscale)
    elif fmt == "meganerf":
        source = load_meganerf(root, downscale or 1)
    elif fmt == "blender":
        source = load_blender(root, downscale or 1, background)
    else:
        source = load_nerfstudio(root, downscale or 1)
    return build_scene(source)

"""Where a worker's scene pixels come from: each split's memory-mapped pixel cache, built on first
use in the cache folder and attached to the scene's views, so training, validation and renders all
read the same file and no process decodes or holds a whole split."""

from __future__ import annotations

import os
from pathlib import Path

from model.scenes.pixel_cache import ensure_cache
from model.scenes.scene import Scene


def pixel_cache() -> Path:
    """LECO_PIXEL_CACHE, default ~/.cache/leco/pixels; the service points it at <data
    dir>/pixel-cache, which a deployment puts on the volume its nodes share."""
    return Path(os.environ.get("LECO_PIXEL_CACHE") or Path.home() / ".cache" / "leco" / "pixels")


def attach_pixel_caches(scene: Scene, splits: tuple[str, ...] | None = None) -> Scene:
    """Open (or build, decoding one image at a time) the cache of each split and attach it to its
    views."""
    log = lambda text: print(f"[leco] {text}", flush=True)
    for name in splits or tuple(scene.splits):
        views = scene.splits[name]
        if views.cache is not None:
            continue
        sizes = [(int(h), int(w)) for h, w in zip(views.cameras.height, views.cameras.width)]
        views.cache = ensure_cache(
            pixel_cache(), scene.root, name, scene.downscale, sizes, views.images.__getitem__, log
        )
    return scene

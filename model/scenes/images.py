"""Reading dataset images with validation and optional integer downscaling."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError
from torch import Tensor

from model.scenes.errors import SceneError
from model.scenes.limits import spend_pixels

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG")
# Checked from the header before any pixel is decoded: a tiny file can claim billions of pixels (a
# decompression bomb). 100 MP is above any drone or DSLR photo a NeRF dataset holds.
MAX_PIXELS = 100_000_000


def find_image(stem: Path) -> Path:
    """The image file for a path given without extension (Blender, Mega-NeRF rgbs/)."""
    if stem.suffix in IMAGE_SUFFIXES and stem.is_file():
        return stem
    for suffix in IMAGE_SUFFIXES:
        candidate = stem.with_name(stem.name + suffix)
        if candidate.is_file():
            return candidate
    raise SceneError(stem, "image is missing (looked for .png/.jpg/.jpeg)")


def read_image(path: Path, *, background: tuple[float, float, float] | None = None) -> Tensor:
    """uint8 (H, W, 3). RGBA is composited on `background` (RGB in [0, 1]; black when None)."""
    try:
        with Image.open(path) as im:
            w, h = im.size
            if w * h > MAX_PIXELS:
                raise SceneError(path, f"image claims {w}x{h} pixels, more pixels than the "
                                       f"{MAX_PIXELS // 10**6} megapixel limit (a corrupt or hostile header?)")
            spend_pixels(path, w * h)
            im.load()
            mode = im.mode
            if mode in ("RGBA", "LA") or (mode == "P" and "transparency" in im.info):
                rgba = np.asarray(im.convert("RGBA"), dtype=np.float32) / 255.0
                if background is None:
                    background = (0.0, 0.0, 0.0)
                alpha = rgba[..., 3:4]
                rgb = rgba[..., :3] * alpha + np.asarray(background, np.float32) * (1.0 - alpha)
                array = np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)
            else:
                array = np.asarray(im.convert("RGB"), dtype=np.uint8)
    except Image.DecompressionBombError as exc:  # PIL's own guard fires first beyond ~179 MP, at open
        raise SceneError(path, f"image claims more pixels than the {MAX_PIXELS // 10**6} megapixel limit "
                               f"(a corrupt or hostile header?): {exc}") from None
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise SceneError(path, f"image is unreadable ({exc.__class__.__name__}: {exc})") from None
    return torch.from_numpy(array.copy())


def downscale_image(image: Tensor, factor: int) -> Tensor:
    """Box-filter downscale by an integer factor; sizes not divisible by it are rounded down."""
    if factor == 1:
        return image
    h, w = image.shape[:2]
    new_w, new_h = max(1, w // factor), max(1, h // factor)
    pil = Image.fromarray(image.numpy()).resize((new_w, new_h), Image.Resampling.BOX)
    return torch.from_numpy(np.asarray(pil, dtype=np.uint8).copy())


def downscale_depth(depth: Tensor, factor: int) -> Tensor:
    """Depth at the pixel centres of the downscaled image (nearest sample: depth must not be blurred)."""
    if factor == 1:
        return depth
    h, w = depth.shape
    new_h, new_w = max(1, h // factor), max(1, w // factor)
    # The centre of a downscaled pixel falls between source pixels for even factors: take the one below.
    rows = (torch.arange(new_h) * factor + factor // 2).clamp(max=h - 1)
    cols = (torch.arange(new_w) * factor + factor // 2).clamp(max=w - 1)
    return depth[rows][:, cols].contiguous()


def check_image_size(path: Path, image: Tensor, width: int, height: int) -> None:
    h, w = image.shape[:2]
    if (w, h) != (width, height):
        raise SceneError(path, f"image is {w}x{h} pixels but its camera says {width}x{height}")

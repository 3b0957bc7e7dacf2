"""Reading dataset images with validation and optional integer downscaling.

Loading a scene reads image headers only (`probe_image`: size, pixel limits, a truncation check on a
PNG's tail); pixels are decoded when an `ImageFile` is called, one image at a time, by whoever needs
them (the pixel cache's build, a test)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError
from torch import Tensor

from model.scenes.errors import SceneError
from model.scenes.limits import MAX_PIXELS, spend_pixels

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG")


def find_image(stem: Path) -> Path:
    """The image file for a path given without extension (Blender, Mega-NeRF rgbs/)."""
    if stem.suffix in IMAGE_SUFFIXES and stem.is_file():
        return stem
    for suffix in IMAGE_SUFFIXES:
        candidate = stem.with_name(stem.name + suffix)
        if candidate.is_file():
            return candidate
    raise SceneError(stem, "image is missing (looked for .png/.jpg/.jpeg)")


def _open_checked(im: Image.Image, path: Path) -> tuple[int, int]:
    w, h = im.size
    if w * h > MAX_PIXELS:
        raise SceneError(
            path,
            f"image claims {w}x{h} pixels, more pixels than the {MAX_PIXELS // 10**6} megapixel "
            "limit (a corrupt or hostile header?)",
        )
    return w, h


# PIL's own guard fires first beyond ~179 MP, at open
def _bomb(path: Path, exc: Exception) -> SceneError:
    return SceneError(
        path,
        f"image claims more pixels than the {MAX_PIXELS // 10**6} megapixel limit (a corrupt or "
        f"hostile header?): {exc}",
    )


# A PNG cut short (an interrupted copy or upload) loses its IEND chunk, which the file's last bytes
# show without decoding. JPEGs are not checked this way: cameras append trailers of any length after
# the end-of-image marker, and refusing those would refuse real captures; a cut JPEG (or any file
# damaged inside) shows when the pixel cache decodes it, which then stops naming the file.
PNG_END = b"IEND\xaeB`\x82"


def _check_tail(path: Path, image_format: str | None) -> None:
    if image_format != "PNG":
        return
    with open(path, "rb") as f:
        f.seek(max(0, path.stat().st_size - 64))
        tail = f.read()
    if PNG_END not in tail:
        raise SceneError(
            path, "image is unreadable (truncated: the PNG has no IEND chunk at its end)"
        )


def probe_image(path: Path) -> tuple[int, int]:
    """(width, height) from the header, charged to the pixel budget, after the size limit and a
    truncation check; nothing is decoded."""
    try:
        with Image.open(path) as im:
            w, h = _open_checked(im, path)
            image_format = im.format
    except Image.DecompressionBombError as exc:
        raise _bomb(path, exc) from None
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise SceneError(path, f"image is unreadable ({exc.__class__.__name__}: {exc})") from None
    _check_tail(path, image_format)
    spend_pixels(path, w * h)
    return w, h


# RGBA is composited in float32 this many pixels at a time, so the temporaries stay near 15 MB
# whatever the image's size; decoding then holds a few bytes per pixel, not the ~50 a whole-image
# float composite took.
COMPOSITE_BLOCK_PIXELS = 1 << 18


def _composite(rgba: np.ndarray, background: tuple[float, float, float]) -> np.ndarray:
    """uint8 (H, W, 3) of uint8 (H, W, 4) over `background`, in row blocks."""
    out = np.empty(rgba.shape[:2] + (3,), np.uint8)
    behind = np.asarray(background, np.float32)
    rows = max(1, COMPOSITE_BLOCK_PIXELS // max(1, rgba.shape[1]))
    for top in range(0, rgba.shape[0], rows):
        block = rgba[top : top + rows].astype(np.float32) / 255.0
        alpha = block[..., 3:4]
        rgb = block[..., :3] * alpha + behind * (1.0 - alpha)
        out[top : top + rows] = np.clip(np.round(rgb * 255.0), 0, 255)
    return out


def read_image(path: Path, *, background: tuple[float, float, float] | None = None) -> Tensor:
    """uint8 (H, W, 3). RGBA is composited on `background` (RGB in [0, 1]; black when None)."""
    try:
        with Image.open(path) as im:
            _open_checked(im, path)
            im.load()
            mode = im.mode
            if mode in ("RGBA", "LA") or (mode == "P" and "transparency" in im.info):
                rgba = np.asarray(im if mode == "RGBA" else im.convert("RGBA"))
                array = _composite(rgba, background or (0.0, 0.0, 0.0))
            else:
                # a writable copy
                array = np.array(im if mode == "RGB" else im.convert("RGB"), dtype=np.uint8)
    except Image.DecompressionBombError as exc:
        raise _bomb(path, exc) from None
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise SceneError(path, f"image is unreadable ({exc.__class__.__name__}: {exc})") from None
    return torch.from_numpy(array)


def downscaled_size(width: int, height: int, factor: int) -> tuple[int, int]:
    """(width, height) after `downscale_image` by `factor`: rounded down, at least 1."""
    return max(1, width // factor), max(1, height // factor)


@dataclass(frozen=True)
class ImageFile:
    """One dataset image, decoded on call: read, checked against its probed size, composited,
    downscaled."""

    path: Path
    width: int  # of the file, as probed
    height: int
    factor: int = 1
    background: tuple[float, float, float] | None = None

    @property
    def size(self) -> tuple[int, int]:
        """(height, width) of the decoded, downscaled image."""
        w, h = downscaled_size(self.width, self.height, self.factor)
        return h, w

    def __call__(self) -> Tensor:
        image = read_image(self.path, background=self.background)
        # the file changed since it was probed
        check_image_size(self.path, image, self.width, self.height)
        return downscale_image(image, self.factor)


def downscale_image(image: Tensor, factor: int) -> Tensor:
    """Box-filter downscale by an integer factor; sizes not divisible by it are rounded down."""
    if factor == 1:
        return image
    h, w = image.shape[:2]
    new_w, new_h = downscaled_size(w, h, factor)
    pil = Image.fromarray(image.numpy()).resize((new_w, new_h), Image.Resampling.BOX)
    return torch.from_numpy(np.asarray(pil, dtype=np.uint8).copy())


def downscale_depth(depth: Tensor, factor: int) -> Tensor:
    """Depth at the pixel centres of the downscaled image (nearest sample: depth must not be
    blurred)."""
    if factor == 1:
        return depth
    h, w = depth.shape
    new_h, new_w = max(1, h // factor), max(1, w // factor)
    # The centre of a downscaled pixel falls between source pixels for even factors: take the one
    # below.
    rows = (torch.arange(new_h) * factor + factor // 2).clamp(max=h - 1)
    cols = (torch.arange(new_w) * factor + factor // 2).clamp(max=w - 1)
    return depth[rows][:, cols].contiguous()


def check_image_size(path: Path, image: Tensor | tuple[int, int], width: int, height: int) -> None:
    """The image (or its probed (width, height)) has the size its camera says."""
    w, h = (image.shape[1], image.shape[0]) if isinstance(image, Tensor) else image
    if (w, h) != (width, height):
        raise SceneError(path, f"image is {w}x{h} pixels but its camera says {width}x{height}")

"""Which of an LLFF capture's image folders (images, images_4, ...) serves a downscale: read by the
loader and, at submit time, by the API (which loads no PyTorch)."""

from __future__ import annotations


def folder_factor(factors, downscale: int) -> int | None:
    """The largest image-folder factor that `downscale` is a multiple of (resizing the least), else
    None."""
    usable = [f for f in factors if downscale % f == 0]
    return max(usable) if usable else None

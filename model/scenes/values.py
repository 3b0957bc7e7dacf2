"""Typed, bounded, finite values from a dataset's metadata. Every reader parses what a file says
through these before using it, so a broken or hostile file is refused with a SceneError naming the
file and the field, never a TypeError, an overflow or a NaN bound later in a worker. Sizes are
checked before anything is converted, and no message echoes the data: a value is described by its
type and shape, or a short repr."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from model.scenes.errors import SceneError

# |a position| in source units. float64 maths is exact far beyond, and after normalisation
# everything is float32.
MAX_COORDINATE = 1e9
# Focal length against the image's larger side: 0.01 is a ~179 degree pinhole, 1e4 a ~0.006 degree
# telephoto.
MIN_FOCAL_RATIO, MAX_FOCAL_RATIO = 1e-2, 1e4
MAX_PRINCIPAL_OFFSET = 100.0  # |principal point - image centre| in image sizes
MAX_DISTORTION = 10.0  # |k1|, |k2|, |p1|, |p2| of OpenCV's model (real lenses: well under 1)
MAX_IMAGE_SIDE = 65_535
MAX_ELEMENTS = 4096  # a camera's array fields hold at most 16 numbers; anything this big is not one
SHORT = 40  # characters of a string value shown in a message


def describe(raw: object) -> str:
    """A value as a message may show it: its kind and size, never its contents beyond a short
    repr."""
    if isinstance(raw, (Tensor, np.ndarray)):
        return f"an array of shape {tuple(raw.shape)} ({raw.dtype})"
    if isinstance(raw, (list, tuple, dict)):
        return f"a {type(raw).__name__} of {len(raw)} item(s)"
    if isinstance(raw, str):
        return repr(raw) if len(raw) <= SHORT else f"a string of {len(raw):,} characters"
    if raw is None or isinstance(raw, (bool, int, float)):
        text = repr(raw)
        return text if len(text) <= SHORT else f"a number of {len(text):,} digits"
    return f"a {type(raw).__name__}"


def number(
    path: Path, raw: object, name: str, lo: float = -MAX_COORDINATE, hi: float = MAX_COORDINATE
) -> float:
    """A finite real number in [lo, hi]; JSON's null, booleans, lists, objects and numeric strings
    are refused."""
    if isinstance(raw, bool) or not isinstance(raw, (int, float, np.integer, np.floating)):
        if not (isinstance(raw, Tensor) and raw.numel() == 1 and not raw.dtype.is_complex):
            raise SceneError(path, f"{name} must be a number, got {describe(raw)}")
    try:
        value = float(raw)
    except OverflowError:  # an int of hundreds of digits
        raise SceneError(path, f"{name} must be a finite number, got {describe(raw)}") from None
    if not math.isfinite(value):
        raise SceneError(path, f"{name} must be finite, got {value}")
    if not lo <= value <= hi:
        raise SceneError(path, f"{name} must be in [{lo:g}, {hi:g}], got {value:g}")
    return value


def integer(path: Path, raw: object, name: str, lo: int, hi: int) -> int:
    """A whole number in [lo, hi] (a float that is whole, as JSON writers sometimes give, is
    accepted)."""
    value = number(path, raw, name, lo, hi)
    if value != int(value):
        raise SceneError(path, f"{name} must be a whole number, got {value:g}")
    return int(value)


def array(
    path: Path,
    raw: object,
    name: str,
    shapes: tuple[tuple[int, ...], ...],
    bound: float = MAX_COORDINATE,
) -> Tensor:
    """A float64 tensor of one of `shapes`, finite, every entry within +-bound. Its size and dtype
    are read before anything is converted: a strided view of one stored number claiming millions is
    refused as such."""
    if isinstance(raw, (Tensor, np.ndarray)):
        shape, numel = tuple(raw.shape), int(np.prod(raw.shape, dtype=np.float64))
        real = (
            (not raw.dtype.is_complex and raw.dtype != torch.bool)
            if isinstance(raw, Tensor)
            else raw.dtype.kind in "iuf"
        )
        if not real:
            raise SceneError(path, f"{name} must hold real numbers, got {describe(raw)}")
    elif isinstance(raw, (list, tuple)):
        shape = _nested_shape(path, raw, name)
        numel = math.prod(shape)
    else:
        raise SceneError(path, f"{name} must be an array of numbers, got {describe(raw)}")
    if numel > MAX_ELEMENTS or math.prod(shape) not in {math.prod(s) for s in shapes}:
        wanted = " or ".join("x".join(map(str, s)) for s in shapes)
        raise SceneError(path, f"{name} must be {wanted} numbers, got {describe(raw)}")
    try:
        values = torch.as_tensor(
            np.asarray(raw, dtype=np.float64) if isinstance(raw, (list, tuple)) else raw
        )
    except (TypeError, ValueError):
        raise SceneError(path, f"{name} must be an array of numbers, got {describe(raw)}") from None
    values = (
        values.to(torch.float64).reshape(next(s for s in shapes if math.prod(s) == numel)).clone()
    )
    if not torch.isfinite(values).all():
        raise SceneError(path, f"{name} has non-finite values (NaN or Inf)")
    if bool((values.abs() > bound).any()):
        raise SceneError(path, f"{name} has values beyond +-{bound:g}")
    return values


def _nested_shape(path: Path, raw: list | tuple, name: str) -> tuple[int, ...]:
    """The shape of a rectangular nested list of numbers, refusing ragged or oversized ones before
    walking them."""
    shape: list[int] = []
    level: object = raw
    while isinstance(level, (list, tuple)):
        shape.append(len(level))
        if math.prod(shape) > MAX_ELEMENTS:
            raise SceneError(path, f"{name} must be a small array of numbers, got {describe(raw)}")
        level = level[0] if len(level) else None
    return tuple(shape)


def image_size(path: Path, width: object, height: object, where: str = "") -> tuple[int, int]:
    return (
        integer(path, width, f"image width{where}", 1, MAX_IMAGE_SIDE),
        integer(path, height, f"image height{where}", 1, MAX_IMAGE_SIDE),
    )


def check_intrinsics(
    path: Path, intrinsics: Tensor, width: int, height: int, where: str = ""
) -> None:
    """fx, fy, cx, cy (pixels) of a width x height image: finite, focal lengths within
    MIN/MAX_FOCAL_RATIO of the larger side, the principal point within MAX_PRINCIPAL_OFFSET image
    sizes of the centre."""
    image_size(path, width, height, where)
    fx, fy, cx, cy = array(path, intrinsics, f"camera intrinsics{where}", ((4,),)).tolist()
    side = max(width, height)
    for label, focal in (("fx", fx), ("fy", fy)):
        if not MIN_FOCAL_RATIO * side <= focal <= MAX_FOCAL_RATIO * side:
            raise SceneError(
                path,
                f"focal length {label}{where} must be {MIN_FOCAL_RATIO:g} to {MAX_FOCAL_RATIO:g} "
                f"times the image's larger side ({side} px), got {focal:g}",
            )
    if (
        abs(cx - width / 2) > MAX_PRINCIPAL_OFFSET * width
        or abs(cy - height / 2) > MAX_PRINCIPAL_OFFSET * height
    ):
        raise SceneError(
            path,
            f"principal point{where} ({cx:g}, {cy:g}) is far outside the {width}x{height} image",
        )


def distortion(path: Path, raw: object, where: str = "") -> Tensor:
    """OpenCV's k1, k2, p1, p2 (missing ones zero), each finite and within MAX_DISTORTION."""
    return array(path, raw, f"distortion{where}", ((4,),), bound=MAX_DISTORTION)


def points(path: Path, raw: Tensor, what: str = "points") -> Tensor:
    """(P, 3) float64 points, finite and within MAX_COORDINATE."""
    if raw.ndim != 2 or raw.shape[1] != 3:
        raise SceneError(path, f"{what} must be a P x 3 array, got {describe(raw)}")
    bad = ~torch.isfinite(raw).all(dim=1) | (raw.abs() > MAX_COORDINATE).any(dim=1)
    if bool(bad.any()):
        first = int(torch.nonzero(bad)[0, 0])
        raise SceneError(
            path,
            f"{what}: {int(bad.sum()):,} are non-finite or beyond +-{MAX_COORDINATE:g} (the first "
            f"is number {first})",
        )
    return raw.double()

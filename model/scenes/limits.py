"""Bounds on what a dataset's files may make a reader allocate, checked before the allocation: array
files (.npy / .npz) by their headers, small metadata files by their size, and the decoded pixels of
a whole scene against a budget (images.py). A tiny hostile file must not claim gigabytes of
memory."""

from __future__ import annotations

import contextlib
import contextvars
import io
import math
import zipfile
from pathlib import Path
from typing import Iterator, cast

import numpy as np

from model.scenes.errors import SceneError

# a camera's .pt metadata or coordinates.pt: a few hundred bytes in practice
MAX_METADATA_BYTES = 1 << 20
MAX_JSON_BYTES = 64 << 20  # transforms.json of tens of thousands of frames
MAX_POINTS_BYTES = 512 << 20  # a sparse point cloud (COLMAP points3D.bin, PLY): millions of points
# one decoded array (a depth map, a 512^3 occupancy grid at 1 byte a cell)
MAX_ARRAY_BYTES = 256 << 20
MAX_NPZ_MEMBERS = 16
# An image's pixels, checked from its header before any is decoded: a tiny file can claim billions
# (a decompression bomb). 100 MP is above any drone or DSLR photo a NeRF dataset holds.
MAX_PIXELS = 100_000_000


def check_file_size(path: Path, limit: int, what: str) -> None:
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise SceneError(path, f"cannot read file ({exc.strerror})") from None
    if size > limit:
        raise SceneError(path, f"{what} is {size:,} bytes; at most {limit:,} are accepted")


def _array_header(
    stream: io.BufferedIOBase, path: Path, max_bytes: int, shape: tuple[int, ...] | None
):
    """(shape, fortran order, dtype) of a .npy stream, checked against the limits; the data is not
    read."""
    try:
        version = np.lib.format.read_magic(stream)
        header = (
            np.lib.format.read_array_header_1_0
            if version == (1, 0)
            else np.lib.format.read_array_header_2_0
        )
        found, fortran, dtype = header(stream)
    except Exception as exc:  # numpy raises ValueError and others for a malformed header
        raise SceneError(
            path, f"not a readable .npy array ({exc.__class__.__name__}: {exc})"
        ) from None
    if dtype.hasobject:
        raise SceneError(path, "array holds Python objects (pickles are not read)")
    if shape is not None and tuple(found) != shape:
        raise SceneError(path, f"array is {tuple(found)} but {shape} was expected")
    nbytes = math.prod(found) * dtype.itemsize
    if nbytes > max_bytes:
        raise SceneError(
            path,
            f"array {tuple(found)} of {dtype} would take {nbytes:,} bytes; at most {max_bytes:,} "
            "are accepted",
        )
    return found, fortran, dtype


def _read_array(
    stream: io.BufferedIOBase, path: Path, max_bytes: int, shape: tuple[int, ...] | None
) -> np.ndarray:
    found, fortran, dtype = _array_header(stream, path, max_bytes, shape)
    nbytes = math.prod(found) * dtype.itemsize
    data, filled = bytearray(nbytes), 0  # writable, so the tensors made from it are too
    view = memoryview(data)
    while filled < nbytes:
        got = stream.readinto(view[filled:])
        if not got:
            raise SceneError(path, f"array is truncated: {filled:,} of {nbytes:,} bytes")
        filled += got
    array = np.frombuffer(data, dtype=dtype, count=math.prod(found))
    return array.reshape(found[::-1]).transpose() if fortran else array.reshape(found)


def read_npy(
    path: Path, max_bytes: int = MAX_ARRAY_BYTES, shape: tuple[int, ...] | None = None
) -> np.ndarray:
    """A .npy file whose header is checked (size, dtype, optionally shape) before its data is
    read."""
    try:
        with open(path, "rb") as stream:
            return _read_array(stream, path, max_bytes, shape)
    except OSError as exc:
        raise SceneError(path, f"cannot read file ({exc.strerror})") from None


def read_npy_header(
    path: Path, max_bytes: int = MAX_ARRAY_BYTES, shape: tuple[int, ...] | None = None
) -> np.dtype:
    """The dtype of a .npy file after its header's checks (as read_npy), without reading the data; a
    file too short to hold the data it declares is refused here too."""
    try:
        with open(path, "rb") as stream:
            found, _, dtype = _array_header(stream, path, max_bytes, shape)
            have, need = path.stat().st_size - stream.tell(), math.prod(found) * dtype.itemsize
    except OSError as exc:
        raise SceneError(path, f"cannot read file ({exc.strerror})") from None
    if have < need:
        raise SceneError(path, f"array is truncated: {have:,} of {need:,} bytes")
    return dtype


def read_npz(path: Path, max_bytes: int = MAX_ARRAY_BYTES) -> dict[str, np.ndarray]:
    """Every array of an .npz archive, each checked as read_npy does; members are read through their
    declared uncompressed size, which zipfile never reads past, so a bomb stops at the limit."""
    try:
        with zipfile.ZipFile(path) as zf:
            members = [m for m in zf.infolist() if m.filename.endswith(".npy")]
            if len(zf.infolist()) > MAX_NPZ_MEMBERS:
                raise SceneError(
                    path, f"holds {len(zf.infolist())} members; at most {MAX_NPZ_MEMBERS} are read"
                )
            arrays = {}
            for member in members:
                if member.file_size > max_bytes + 4096:  # the data plus its header
                    raise SceneError(
                        path,
                        f"member {member.filename!r} is {member.file_size:,} bytes uncompressed; "
                        f"at most {max_bytes:,} are accepted",
                    )
                # ZipFile.open is typed IO[bytes] for its write mode's sake; reading, it gives a
                # ZipExtFile.
                with cast(zipfile.ZipExtFile, zf.open(member)) as stream:
                    arrays[member.filename[:-4]] = _read_array(stream, path, max_bytes, None)
            return arrays
    except SceneError:
        raise
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        raise SceneError(
            path, f"not a readable .npz archive ({exc.__class__.__name__}: {exc})"
        ) from None


_pixels_left: contextvars.ContextVar[list | None] = contextvars.ContextVar(
    "leco_pixels_left", default=None
)


@contextlib.contextmanager
def pixel_budget(max_pixels: int | None, source: str = "LECO_MAX_SCENE_PIXELS") -> Iterator[None]:
    """Within this block (in this thread), images may decode at most `max_pixels` pixels in all;
    None: no budget. The service registers uploads under one, so a few MB of PNGs cannot decode to
    gigabytes; `source` says in the refusal where the budget comes from."""
    token = _pixels_left.set(None if max_pixels is None else [max_pixels, max_pixels, source])
    try:
        yield
    finally:
        _pixels_left.reset(token)


def spend_pixels(path: Path, pixels: int) -> None:
    """Charge an image's pixels (read from its header, before it is decoded) to the current
    budget."""
    budget = _pixels_left.get()
    if budget is None:
        return
    if pixels > budget[0]:
        raise SceneError(
            path,
            f"the scene's images exceed the budget of {budget[1]:,} decoded pixels for one scene "
            f"({budget[2]}); this image alone has {pixels:,}",
        )
    budget[0] -= pixels

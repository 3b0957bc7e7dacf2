"""Sparse SfM points: COLMAP points3D.bin and points3D.txt, and the vertex positions of a PLY file
(nerfstudio's sparse_pc.ply)."""

from __future__ import annotations

import struct
from array import array
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from model.scenes import values
from model.scenes.errors import SceneError
from model.scenes.limits import MAX_POINTS_BYTES, check_file_size

PLY_TYPES = {
    "char": "i1",
    "uchar": "u1",
    "short": "i2",
    "ushort": "u2",
    "int": "i4",
    "uint": "u4",
    "float": "f4",
    "double": "f8",
    "int8": "i1",
    "uint8": "u1",
    "int16": "i2",
    "uint16": "u2",
    "int32": "i4",
    "uint32": "u4",
    "float32": "f4",
    "float64": "f8",
}


def read_colmap_points(path: Path) -> Tensor:
    """xyz (P, 3) float64 of a COLMAP binary points3D file."""
    check_file_size(path, MAX_POINTS_BYTES, "a point file")
    data = path.read_bytes()
    try:
        (count,) = struct.unpack_from("<Q", data, 0)
        # each point takes at least 51 bytes: the header cannot claim more
        if count > (len(data) - 8) // 51:
            raise SceneError(
                path, f"COLMAP points3D.bin claims {count:,} points but holds {len(data):,} bytes"
            )
        offset, xyz = 8, np.empty((count, 3), dtype=np.float64)
        for i in range(count):
            # id u64, xyz 3 f64, rgb 3 u8, error f64, track length u64, then (image id, point2D idx)
            # i32 pairs
            xyz[i] = struct.unpack_from("<3d", data, offset + 8)
            (track,) = struct.unpack_from("<Q", data, offset + 43)
            offset += 51 + 8 * track
    except struct.error:
        raise SceneError(path, "truncated or malformed COLMAP points3D.bin") from None
    if offset > len(data):  # the last point's track runs past the end
        raise SceneError(path, "truncated or malformed COLMAP points3D.bin")
    if offset != len(data):
        raise SceneError(
            path, f"malformed COLMAP points3D.bin: {len(data) - offset} trailing bytes"
        )
    return values.points(path, torch.from_numpy(xyz), "COLMAP points")


def text_lines(path: Path, limit: int, what: str) -> Iterator[tuple[int, str]]:
    """(line number, line without its end) of a text file (COLMAP's .txt models), read as they are
    walked, after the file's size check; a file that is not UTF-8 is refused."""
    check_file_size(path, limit, what)
    try:
        with open(path, encoding="utf-8") as stream:
            for number, line in enumerate(stream, 1):
                yield number, line.rstrip("\n")
    except UnicodeDecodeError:
        raise SceneError(path, f"{what} is not UTF-8 text") from None
    except OSError as exc:
        raise SceneError(path, f"cannot read file ({exc.strerror})") from None


def read_colmap_points_text(path: Path) -> Tensor:
    """xyz (P, 3) float64 of a COLMAP text points3D file: one point a line, POINT3D_ID X Y Z R G B
    ERROR then its track as (IMAGE_ID POINT2D_IDX) pairs; lines starting with # are comments."""
    xyz = array("d")
    for number, line in text_lines(path, MAX_POINTS_BYTES, "a point file"):
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        if len(words) < 8 or len(words) % 2:
            raise SceneError(
                path,
                f"truncated or malformed COLMAP points3D.txt: line {number} has {len(words)} "
                "field(s), not POINT3D_ID X Y Z R G B ERROR and (IMAGE_ID POINT2D_IDX) pairs",
            )
        try:
            xyz.extend(float(w) for w in words[1:4])
        except ValueError:
            raise SceneError(
                path, f"malformed COLMAP points3D.txt: X Y Z on line {number} are not numbers"
            ) from None
    points = torch.from_numpy(np.frombuffer(xyz, dtype=np.float64).copy()).reshape(-1, 3)
    return values.points(path, points, "COLMAP points")


def read_ply_points(path: Path) -> Tensor:
    """Vertex x, y, z (P, 3) float64 of an ASCII or binary little-endian PLY file."""
    check_file_size(path, MAX_POINTS_BYTES, "a point file")
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise SceneError(path, "not a PLY file (no 'ply' magic or no end_header)")
    header = data[:end].decode("ascii", errors="replace").splitlines()
    fmt, count, props, in_vertex = None, 0, [], False
    for line in header:
        words = line.split()
        if words[:1] == ["format"] and len(words) >= 2:
            fmt = words[1]
        elif words[:1] == ["element"]:
            if len(words) != 3 or not words[2].isdigit():
                raise SceneError(
                    path,
                    f"malformed PLY element line {line.strip()[:80]!r} (element <name> <count>)",
                )
            in_vertex = words[1] == "vertex"
            if in_vertex:
                count = int(words[2])
        elif words[:1] == ["property"] and in_vertex:
            if len(words) != 3 or words[1] not in PLY_TYPES:
                raise SceneError(path, f"unsupported PLY vertex property: {line.strip()[:80]!r}")
            props.append((words[2], PLY_TYPES[words[1]]))
    names = [p[0] for p in props]
    if not {"x", "y", "z"} <= set(names):
        raise SceneError(path, "PLY vertices need x, y and z properties")
    if count == 0:
        raise SceneError(path, "PLY file has no vertices (element vertex 0)")
    body = data[end + len(b"end_header\n") :]
    try:
        if fmt == "binary_little_endian":
            vertices = np.frombuffer(
                body, dtype=np.dtype([(n, "<" + t) for n, t in props]), count=count
            )
            xyz = np.stack([vertices[a].astype(np.float64) for a in "xyz"], axis=1)
        elif fmt == "ascii":
            rows = np.loadtxt(body.decode().splitlines()[:count], ndmin=2)
            xyz = rows[:, [names.index(a) for a in "xyz"]].astype(np.float64)
        else:
            raise SceneError(
                path, f"unsupported PLY format {fmt!r} (ascii or binary_little_endian)"
            )
    except ValueError as exc:
        raise SceneError(path, f"truncated or malformed PLY vertex data ({exc})") from None
    if len(xyz) < count:
        raise SceneError(path, f"PLY file declares {count:,} vertices but holds {len(xyz):,}")
    return values.points(path, torch.from_numpy(np.ascontiguousarray(xyz)), "PLY vertices")

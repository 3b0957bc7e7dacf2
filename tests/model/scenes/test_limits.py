"""A dataset's small files cannot make a reader allocate what their headers claim, and a scene's
images decode within a pixel budget. Each refusal is a SceneError naming the file and the limit,
raised before the allocation."""

import io
import struct
import zipfile

import numpy as np
import pytest

from model.scenes import load_scene
from model.scenes.errors import SceneError
from model.scenes.formats.points import read_colmap_points
from model.scenes.limits import pixel_budget, read_npy, read_npz


def npy_bytes(header: str) -> bytes:
    """A version 1.0 .npy header (padded as numpy pads it) with no data after it."""
    body = header.encode("latin1")
    pad = 64 - (10 + len(body) + 1) % 64
    body += b" " * pad + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(body)) + body


def test_an_array_header_claiming_gigabytes_is_refused_before_anything_is_read(tmp_path):
    path = tmp_path / "depth.npy"
    path.write_bytes(
        npy_bytes("{'descr': '<f8', 'fortran_order': False, 'shape': (100000, 100000), }")
    )
    with pytest.raises(SceneError, match=r"would take 80,000,000,000 bytes; at most"):
        read_npy(path)
    with pytest.raises(SceneError, match=r"is \(100000, 100000\) but \(4, 5\) was expected"):
        read_npy(path, shape=(4, 5))


def test_arrays_of_objects_truncated_arrays_and_garbage_are_refused(tmp_path):
    path = tmp_path / "a.npy"
    path.write_bytes(npy_bytes("{'descr': '|O', 'fortran_order': False, 'shape': (3,), }"))
    with pytest.raises(SceneError, match="Python objects"):
        read_npy(path)
    np.save(path, np.arange(12.0).reshape(3, 4))
    path.write_bytes(path.read_bytes()[:-8])
    with pytest.raises(SceneError, match="truncated: 88 of 96 bytes"):
        read_npy(path)
    path.write_bytes(b"not an array")
    with pytest.raises(SceneError, match="not a readable .npy array"):
        read_npy(path)


def test_well_formed_arrays_read_back_exactly_in_either_memory_order(tmp_path):
    array = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    for i, a in enumerate((array, np.asfortranarray(array))):
        np.save(tmp_path / f"{i}.npy", a)
        assert np.array_equal(read_npy(tmp_path / f"{i}.npy", shape=(2, 3, 4)), array)
    np.savez_compressed(
        tmp_path / "grid.npz", occupied=np.ones((8, 8, 8), bool), world_from_grid=np.eye(4)
    )
    arrays = read_npz(tmp_path / "grid.npz")
    assert arrays["occupied"].all() and np.array_equal(arrays["world_from_grid"], np.eye(4))


def test_an_npz_member_bomb_is_refused_by_its_declared_size(tmp_path):
    path = tmp_path / "occupancy.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        buffer = io.BytesIO()
        np.save(buffer, np.zeros(300 << 20, dtype=np.uint8))  # 300 MiB of zeros deflate to ~300 KiB
        zf.writestr("occupied.npy", buffer.getvalue())
    assert path.stat().st_size < 1 << 20
    with pytest.raises(SceneError, match="member 'occupied.npy' is 314,572,928 bytes uncompressed"):
        read_npz(path)
    with zipfile.ZipFile(path, "w") as zf:
        for i in range(17):
            zf.writestr(f"a{i}.npy", b"")
    with pytest.raises(SceneError, match="holds 17 members; at most 16"):
        read_npz(path)


def test_a_colmap_point_file_cannot_claim_more_points_than_it_holds(tmp_path):
    path = tmp_path / "points3D.bin"
    path.write_bytes(struct.pack("<Q", 2**60) + b"\0" * 100)
    with pytest.raises(
        SceneError, match="claims 1,152,921,504,606,846,976 points but holds 108 bytes"
    ):
        read_colmap_points(path)


def test_a_scene_decodes_within_its_pixel_budget(tiny_scene):
    total = sum(
        image.shape[0] * image.shape[1]
        for views in tiny_scene.splits.values()
        for image in views.images
    )
    with pixel_budget(total):
        load_scene(tiny_scene.root)  # exactly the budget: loads
    with (
        pixel_budget(total - 1),
        pytest.raises(SceneError, match=rf"budget of {total - 1:,} decoded pixels"),
    ):
        load_scene(tiny_scene.root)
    load_scene(tiny_scene.root)  # no budget outside the block

"""Malformed and hostile scene files of every format are refused with a SceneError that names the
file and the field (a 422 from the service), never another exception, a NaN bound or a worker
failure later; nothing they hold is converted before its size is known, and no message echoes their
data."""

import json
import math
import struct
from dataclasses import replace

import numpy as np
import pytest
import torch

from model.scenes import SceneError, load_scene, values
from tests.model.scenes.test_bad_input import blender, expect, llff, meganerf  # noqa: F401 (fixtures)
from tests.model.scenes.test_colmap import tiny_model, write_bin, write_scene
from tests.model.scenes.test_nerfstudio import nerfstudio, rewrite  # noqa: F401 (fixture)

MAX_MESSAGE = 400  # every refusal below is a sentence, not a dump of the file


def refused(root, match, file):
    error = expect(root, match, file)
    assert len(str(error)) < MAX_MESSAGE + len(str(root)), str(error)[:MAX_MESSAGE]
    return error


# --- nerfstudio transforms.json
# ------------------------------------------------------------------------------

NERFSTUDIO_CASES = {
    "k1 a list": ({"k1": [1]}, "field 'k1'.*must be a number, got a list"),
    "k3 null": ({"k3": None}, "field 'k3'.*must be a number, got None"),
    "k2 NaN": ({"k2": float("nan")}, "field 'k2'.*must be finite"),
    "p1 huge": ({"p1": 50.0}, r"distortion.*beyond \+-10"),
    "train_filenames an int": (
        {"train_filenames": 5},
        "'train_filenames' must be a list of file paths",
    ),
    "val_filenames of numbers": (
        {"val_filenames": [1, 2]},
        "'val_filenames' must be a list of file paths",
    ),
    "fl_x 1e39": ({"fl_x": 1e39}, r"field 'fl_x'.*must be in"),
    "fl_x 1e-50": ({"fl_x": 1e-50}, "focal length fx.*must be 0.01 to 10000 times"),
    "fl_y negative": ({"fl_y": -5.0}, "focal length fy"),
    "cx far outside": ({"cx": 1e8}, "principal point.*far outside"),
    "w zero": ({"w": 0}, "image width.*must be in"),
    "h fractional": ({"h": 200.5}, "image height.*must be a whole number"),
    "w a string": ({"w": "200"}, "image width.*must be a number, got '200'"),
    "w a bool": ({"w": True}, "image width.*must be a number, got True"),
    "w of 400 digits": ({"w": 10**400}, "image width.*a number of 401 digits"),
}


@pytest.mark.parametrize("case", NERFSTUDIO_CASES)
def test_nerfstudio_fields_are_typed_and_bounded(nerfstudio, case):  # noqa: F811
    change, match = NERFSTUDIO_CASES[case]
    rewrite(nerfstudio, lambda d: d.update(change))
    refused(nerfstudio, match, "transforms.json")


def test_nerfstudio_file_path_and_translation(nerfstudio):  # noqa: F811
    rewrite(nerfstudio, lambda d: d["frames"][2].update(file_path=["images/r_0.png"]))
    refused(nerfstudio, r"file_path \(frame 2\) must be a string", "transforms.json")
    rewrite(nerfstudio, lambda d: d["frames"][2].update(file_path="images/r_2.png"))
    rewrite(nerfstudio, lambda d: d["frames"][3]["transform_matrix"][0].__setitem__(3, 1e308))
    refused(nerfstudio, r"camera position \(frame 3\) is beyond", "transforms.json")


def ply(points, count=None, header_extra=()):
    lines = [
        "ply",
        "format ascii 1.0",
        f"element vertex {len(points) if count is None else count}",
        *header_extra,
        "property float x",
        "property float y",
        "property float z",
        "end_header",
    ]
    return ("\n".join(lines) + "\n" + "".join(f"{x} {y} {z}\n" for x, y, z in points)).encode()


def lego_points(n=200, seed=0):
    return (np.random.default_rng(seed).uniform(-1, 1, (n, 3))).tolist()


PLY_CASES = {
    "element without a count": (
        lambda: ply(lego_points()).replace(b"element vertex 200", b"element vertex"),
        "malformed PLY element line",
    ),
    "element count not a number": (
        lambda: ply(lego_points()).replace(b"vertex 200", b"vertex lots"),
        "malformed PLY element line",
    ),
    "property without a name": (
        lambda: ply(lego_points()).replace(b"property float z", b"property float"),
        "unsupported PLY vertex property",
    ),
    "no vertices": (lambda: ply([], count=0), r"no vertices \(element vertex 0\)"),
    "fewer vertices than declared": (
        lambda: ply(lego_points(), count=300),
        "declares 300 vertices but holds 200",
    ),
    "a NaN point": (
        lambda: ply(lego_points()[:-1] + [[float("nan"), 0, 0]]),
        "1 are non-finite.*number 199",
    ),
    "an infinite point": (
        lambda: ply([[float("inf"), 0, 0]] + lego_points()),
        "non-finite or beyond.*number 0",
    ),
    "a point at 1e308": (lambda: ply(lego_points() + [[1e308, 0, 0]]), "non-finite or beyond"),
}


@pytest.mark.parametrize("case", PLY_CASES)
def test_ply_points_are_parsed_strictly(nerfstudio, case):  # noqa: F811
    make, match = PLY_CASES[case]
    (nerfstudio / "sparse_pc.ply").write_bytes(make())
    rewrite(nerfstudio, lambda d: d.update(ply_file_path="sparse_pc.ply"))
    refused(nerfstudio, match, "sparse_pc.ply")


@pytest.mark.parametrize(
    "points", [[[0.1, 0.2, 0.3]], [[0.1, 0.2, 0.3]] * 50], ids=["one point", "50 identical"]
)
def test_degenerate_point_sets_are_refused_not_nan_bounds(nerfstudio, points):  # noqa: F811
    (nerfstudio / "sparse_pc.ply").write_bytes(ply(points))
    rewrite(nerfstudio, lambda d: d.update(ply_file_path="sparse_pc.ply"))
    refused(nerfstudio, "cannot find the foreground: its .* span no volume", "ns")


def test_good_ply_still_loads(nerfstudio):  # noqa: F811
    (nerfstudio / "sparse_pc.ply").write_bytes(ply(lego_points()))
    rewrite(nerfstudio, lambda d: d.update(ply_file_path="sparse_pc.ply"))
    scene = load_scene(nerfstudio)
    assert scene.bounds.source == "sparse_points" and torch.isfinite(scene.bounds.aabb).all()
    assert float((scene.bounds.aabb[1] - scene.bounds.aabb[0]).min()) > 0


# --- Mega-NeRF .pt files
# ------------------------------------------------------------------------------------


def edit_meta(root, change, name="train/metadata/000000.pt"):
    meta = torch.load(root / name, weights_only=True)
    meta.update(change)
    torch.save(meta, root / name)


META_CASES = {
    "intrinsics a string": (
        {"intrinsics": "abcd"},
        "intrinsics.*must be an array of numbers, got 'abcd'",
    ),
    "intrinsics of 5": (
        {"intrinsics": torch.ones(5)},
        r"must be 4 numbers, got an array of shape \(5,\)",
    ),
    "intrinsics complex": (
        {"intrinsics": torch.ones(4, dtype=torch.complex64)},
        "must hold real numbers",
    ),
    "c2w nested list of strings": ({"c2w": [["a"] * 4] * 3}, "c2w must be an array of numbers"),
    "W null": ({"W": None}, "image width must be a number, got None"),
    "H a tensor of 2": ({"H": torch.ones(2)}, "image height must be a number"),
    "distortion NaN": (
        {"distortion": torch.tensor([float("nan"), 0, 0, 0])},
        "distortion has non-finite",
    ),
    "focal 1e-50": (
        {"intrinsics": torch.tensor([1e-50, 1e-50, 8.0, 6.0], dtype=torch.float64)},
        "focal length fx.*must be 0.01 to 10000 times",
    ),
    "focal float32 overflow": (
        {"intrinsics": torch.tensor([1e39, 1e39, 8.0, 6.0], dtype=torch.float64)},
        r"beyond \+-1e\+09",
    ),
    "strided bomb": (
        {"intrinsics": torch.zeros(1).expand(5000, 5000)},
        r"got an array of shape \(5000, 5000\)",
    ),
}


@pytest.mark.parametrize("case", META_CASES)
def test_meganerf_metadata_is_typed_and_bounded(meganerf, case):  # noqa: F811
    change, match = META_CASES[case]
    edit_meta(meganerf, change)
    refused(meganerf, match, "000000.pt")


COORDINATE_CASES = {
    "origin null": ({"origin_drb": None}, "origin_drb must be an array of numbers, got None"),
    "origin of 2": ({"origin_drb": [0.0, 1.0]}, "origin_drb must be 3 numbers"),
    "origin NaN": (
        {"origin_drb": torch.tensor([0.0, float("nan"), 0.0])},
        "origin_drb has non-finite",
    ),
    "origin strided bomb": (
        {"origin_drb": torch.zeros(1).expand(10**6, 10**6)},
        r"got an array of shape \(1000000, 1000000\)",
    ),
    "scale a list": (
        {"pose_scale_factor": [1, 2]},
        "pose_scale_factor must be a number, got a list of 2",
    ),
    "scale zero": ({"pose_scale_factor": 0.0}, "pose_scale_factor must be in"),
}


@pytest.mark.parametrize("case", COORDINATE_CASES)
def test_meganerf_coordinates_are_typed_and_bounded(meganerf, case):  # noqa: F811
    change, match = COORDINATE_CASES[case]
    data = torch.load(meganerf / "coordinates.pt", weights_only=True)
    data.update(change)
    torch.save(data, meganerf / "coordinates.pt")
    refused(meganerf, match, "coordinates.pt")


def test_a_strided_bomb_is_refused_before_it_is_converted(meganerf):  # noqa: F811
    """Before: the expanded view was converted to float64 (200 MB at 5000^2, 8 TB at 10^6 squared)
    and its values formatted into the message."""
    import resource

    edit_meta(meganerf, {"intrinsics": torch.zeros(1).expand(20000, 20000)})  # 3.2 GB as float64
    assert (meganerf / "train/metadata/000000.pt").stat().st_size < 4096
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    error = refused(meganerf, "intrinsics", "000000.pt")
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert grown_mb < 256, f"refusing it grew the process by {grown_mb:.0f} MB"
    assert "0., 0." not in str(error) and "tensor(" not in str(error)


GT_CASES = {
    "a list": ([1, 2, 3], "must hold a JSON object, got a list of 3"),
    "a NaN seed": (
        {"generator": "leco-synthetic-city", "seed": float("nan")},
        "field 'seed' must be finite",
    ),
    "a seed of 1e300": ({"seed": 1e300}, "field 'seed' must be in"),
    "a long generator": (
        {"generator": "x" * 10_000},
        "field 'generator' must be a string of at most 64",
    ),
    "a preset that is a list": ({"preset": [1]}, "field 'preset' must be an object"),
    "a NaN preset value": (
        {"preset": {"altitude": float("nan")}},
        r"field 'preset.altitude' must be finite",
    ),
}


@pytest.mark.parametrize("case", GT_CASES)
def test_meganerf_gt_scene_json_is_typed_and_short(meganerf, case):  # noqa: F811
    content, match = GT_CASES[case]
    (meganerf / "gt").mkdir()
    (meganerf / "gt" / "scene.json").write_text(json.dumps(content))
    refused(meganerf, match, "scene.json")


def test_an_8_mib_gt_scene_json_is_refused_by_its_size(meganerf):  # noqa: F811
    (meganerf / "gt").mkdir()
    (meganerf / "gt" / "scene.json").write_text(json.dumps({"boxes": [[0.5] * 3] * 600_000}))
    assert (meganerf / "gt" / "scene.json").stat().st_size > 8 << 20
    refused(meganerf, "gt/scene.json is .* bytes; at most", "scene.json")


def test_a_good_gt_scene_json_keeps_only_the_generator(meganerf):  # noqa: F811
    (meganerf / "gt").mkdir()
    (meganerf / "gt" / "scene.json").write_text(
        json.dumps(
            {
                "generator": "g",
                "preset": {"name": "city", "views": 80, "depth_maps": True},
                "seed": 3,
                "boxes": [[0.0] * 3] * 100,
            }
        )
    )
    assert load_scene(meganerf).extras["generator"] == {
        "generator": "g",
        "preset": {"name": "city", "views": 80, "depth_maps": True},
        "seed": 3,
    }


# --- LLFF poses_bounds.npy
# ----------------------------------------------------------------------------------


def edit_poses(root, row, column, value):
    poses = np.load(root / "poses_bounds.npy")
    poses[row, column] = value
    np.save(root / "poses_bounds.npy", poses)


LLFF_CASES = {  # columns: 3x5 [R | t | hwf] row-major, so h=4, w=9, focal=14; near=15, far=16
    "focal 0": (14, 0.0, r"focal length fx \(row 2\)"),
    "focal 1e-50": (14, 1e-50, r"focal length fx \(row 2\)"),
    "focal -14": (14, -14.0, r"focal length fx \(row 2\)"),
    "width 0": (9, 0.0, r"image width \(row 2\) must be in"),
    "height 1e12": (4, 1e12, r"image height \(row 2\) must be in"),
    "near 0": (15, 0.0, r"0 < near <= far, not in row\(s\) \[2\]"),
    "far before near": (16, 1e-6, r"0 < near <= far, not in row\(s\) \[2\]"),
    "translation 1e300": (3, 1e300, r"camera position \(row 2\) is beyond"),
}


@pytest.mark.parametrize("case", LLFF_CASES)
def test_llff_rows_are_bounded(llff, case):  # noqa: F811
    column, value, match = LLFF_CASES[case]
    edit_poses(llff, 2, column, value)
    refused(llff, match, "poses_bounds.npy")


# --- the value layer itself
# ---------------------------------------------------------------------------------


def test_describe_never_echoes_data():
    bomb = torch.zeros(1).expand(10**6, 10**6)
    assert values.describe(bomb) == "an array of shape (1000000, 1000000) (torch.float32)"
    assert values.describe("x" * 1000) == "a string of 1,000 characters"
    assert values.describe([0.0] * 10**5) == "a list of 100000 item(s)"
    assert values.describe(10**100) == "a number of 101 digits"
    assert values.describe(1.5) == "1.5"


def test_array_accepts_what_readers_give():
    path = "f"
    assert values.array(path, [1, 2, 3], "v", ((3,),)).dtype == torch.float64
    assert values.array(path, np.arange(12.0).reshape(3, 4), "v", ((3, 4),)).shape == (3, 4)
    assert values.array(path, torch.eye(4)[:3], "v", ((3, 4), (4, 4))).shape == (3, 4)
    # 16 numbers: the 4x4 shape
    assert values.array(path, torch.ones(16), "v", ((3, 4), (4, 4))).shape == (4, 4)
    with pytest.raises(SceneError, match="v must be 3 numbers, got a list of 2"):
        values.array(path, [[1, 2, 3], [4, 5, 6]], "v", ((3,),))
    with pytest.raises(SceneError, match="must be a small array"):
        values.array(path, [[0.0] * 100] * 100, "v", ((3,),))
    assert math.isclose(values.number(path, np.float32(2.5), "n"), 2.5)


# --- COLMAP sparse/0 models
# ---------------------------------------------------------------------------------


def with_camera(**change):
    return lambda m: replace(m, cameras=[replace(m.cameras[0], **change)])


COLMAP_MODEL_CASES = {  # an edit of the tiny model, rewritten as binary over its good files
    "width 0": (
        with_camera(width=0),
        "cameras.bin",
        r"image width \(camera 1\) must be in \[1, 65535\], got 0",
    ),
    "width 2**64 - 1": (
        with_camera(width=2**64 - 1),
        "cameras.bin",
        r"image width \(camera 1\) must be in",
    ),
    "focal 1e-50": (
        with_camera(params=[1e-50, 7.5, 4.25, 2.75]),
        "cameras.bin",
        r"focal length fx \(camera 1\) must be 0.01 to 10000 times",
    ),
    "focal inf": (
        with_camera(params=[math.inf, 7.5, 4.25, 2.75]),
        "cameras.bin",
        "fx of camera 1 must be finite",
    ),
    "principal point far outside": (
        with_camera(params=[8.5, 7.5, 1e8, 2.75]),
        "cameras.bin",
        r"principal point \(camera 1\) .* is far outside the 8x6 image",
    ),
    "k1 50": (
        with_camera(model="OPENCV", params=[8.0, 8.0, 4.0, 3.0, 50.0, 0, 0, 0]),
        "cameras.bin",
        r"distortion \(camera 1\) has values beyond \+-10",
    ),
    "a translation of 1e300": (
        lambda m: m.edit_image(0, tvec=[1e300, 0.0, 0.0]),
        "images.bin",
        r"tvec \(image 100 'frame_00002.png'\) has values beyond \+-1e\+09",
    ),
    "a name of 5000 bytes": (
        lambda m: m.edit_image(0, name="a" * 5000),
        "images.bin",
        "truncated or malformed COLMAP images.bin",
    ),
}


@pytest.mark.parametrize("case", COLMAP_MODEL_CASES)
def test_colmap_binary_fields_are_bounded(tmp_path, case):
    edit, file, match = COLMAP_MODEL_CASES[case]
    model = tiny_model(n=3)
    root = write_scene(tmp_path / "colmap", model)
    write_bin(root / "sparse" / "0", edit(model))
    refused(root, match, file)


def after_first_name(data: bytes) -> int:
    """Offset of the first image's num_points2D in images.bin."""
    return data.index(b"\0", 8 + 4 + 56 + 4) + 1


COLMAP_BYTE_CASES = {  # file, its bytes -> hostile bytes, what is said
    "images claimed 2**64 - 1": (
        "images.bin",
        lambda d: struct.pack("<Q", 2**64 - 1) + d[8:],
        "claims 18,446,744,073,709,551,615 images",
    ),
    "num_points2D 2**63": (
        "images.bin",
        lambda d: (
            d[: after_first_name(d)] + struct.pack("<Q", 2**63) + d[after_first_name(d) + 8 :]
        ),
        "truncated or malformed COLMAP images.bin",
    ),
    "a name that is not UTF-8": (
        "images.bin",
        lambda d: d[:72] + b"\xff" + d[73:],
        "the name of image 100 is not UTF-8",
    ),
    "a track of 2**62 in the last point": (
        "points3D.bin",
        # the last point: 43 bytes, its u64 track length, then 2 (IMAGE_ID, POINT2D_IDX) pairs
        lambda d: d[: len(d) - 24] + struct.pack("<Q", 2**62) + d[len(d) - 16 :],
        "truncated or malformed COLMAP points3D.bin",
    ),
}


@pytest.mark.parametrize("case", COLMAP_BYTE_CASES)
def test_colmap_binary_layout_is_checked(tmp_path, case):
    name, edit, match = COLMAP_BYTE_CASES[case]
    root = write_scene(tmp_path / "colmap", tiny_model(n=3))
    path = root / "sparse" / "0" / name
    path.write_bytes(edit(path.read_bytes()))
    refused(root, match, name)

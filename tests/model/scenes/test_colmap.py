"""The COLMAP reader on tiny models written here, binary and text (8x6 images, a ring of cameras
round a cluster of points): camera models and distortion, poses against the centres and directions
written, the split, downscale, the sparse points, detection, and every bad input refused naming the
file."""

import json
import struct
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pytest
import torch

from model.scenes import SceneError, detect_format, load_scene
from model.scenes.synthetic.writer import save_png
from tests.model.scenes.test_bad_input import expect

W, H = 8, 6
MODEL_IDS = {
    "SIMPLE_PINHOLE": 0,
    "PINHOLE": 1,
    "SIMPLE_RADIAL": 2,
    "RADIAL": 3,
    "OPENCV": 4,
    "OPENCV_FISHEYE": 5,
    "FOV": 7,
}
# model -> (params written, the fx fy cx cy and k1 k2 p1 p2 they stand for)
CAMERA_MODELS = {
    "SIMPLE_PINHOLE": ([8.0, 4.0, 3.0], [8.0, 8.0, 4.0, 3.0], [0, 0, 0, 0]),
    "PINHOLE": ([8.5, 7.5, 4.25, 2.75], [8.5, 7.5, 4.25, 2.75], [0, 0, 0, 0]),
    "SIMPLE_RADIAL": ([9.0, 3.5, 3.25, 0.05], [9.0, 9.0, 3.5, 3.25], [0.05, 0, 0, 0]),
    "RADIAL": ([7.0, 4.5, 2.5, -0.04, 0.01], [7.0, 7.0, 4.5, 2.5], [-0.04, 0.01, 0, 0]),
    "OPENCV": (
        [8.25, 8.75, 3.75, 3.5, 0.02, -0.03, 0.001, -0.002],
        [8.25, 8.75, 3.75, 3.5],
        [0.02, -0.03, 0.001, -0.002],
    ),
}


@dataclass
class Camera:
    id: int
    model: str
    width: int
    height: int
    params: list[float]


@dataclass
class Image:
    id: int
    qvec: list[float]
    tvec: list[float]
    camera_id: int
    name: str
    points2d: list[tuple[float, float, int]] = field(default_factory=list)
    rotation: np.ndarray | None = (
        None  # the world-to-camera rotation qvec was made from (not written)
    )


@dataclass
class Model:
    cameras: list[Camera]
    images: list[Image]
    points: list[list[float]]  # xyz; each point's track is two observations

    def edit_image(self, index: int, **change) -> "Model":
        images = list(self.images)
        images[index] = replace(images[index], **change)
        return replace(self, images=images)


def qvec_of(r: np.ndarray) -> list[float]:
    """Unit quaternion (w, x, y, z) of a rotation matrix (COLMAP's scripts/python rotmat2qvec)."""
    rxx, ryx, rzx, rxy, ryy, rzy, rxz, ryz, rzz = r.flat
    k = (
        np.array(
            [
                [rxx - ryy - rzz, 0, 0, 0],
                [ryx + rxy, ryy - rxx - rzz, 0, 0],
                [rzx + rxz, rzy + ryz, rzz - rxx - ryy, 0],
                [ryz - rzy, rzx - rxz, rxy - ryx, rxx + ryy + rzz],
            ]
        )
        / 3.0
    )
    eigenvalues, eigenvectors = np.linalg.eigh(k)
    q = eigenvectors[[3, 0, 1, 2], np.argmax(eigenvalues)]
    return (q if q[0] >= 0 else -q).tolist()


def look_at(center: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Camera-to-world rotation in OpenCV axes (x right, y down, z forward) aiming at the origin."""
    z = -center / np.linalg.norm(center)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


# COLMAP's world is whatever the reconstruction chose: here y points down, as in many captures
WORLD_UP = np.array([0.0, -1.0, 0.0])


def centres(n: int) -> np.ndarray:
    """A ring of n cameras at radius ~4 round the world's up axis, at varying heights."""
    angle = np.linspace(0, 2 * np.pi, n, endpoint=False)
    radius = 4.0 + 0.3 * np.sin(3 * angle)
    return np.stack([radius * np.cos(angle), -1.0 - 0.4 * np.cos(angle), radius * np.sin(angle)], 1)


def tiny_model(n: int = 10, models: tuple[str, ...] = ("PINHOLE",), points: int = 40) -> Model:
    """n images of `models`' cameras, in turn, and `points` sparse points in a cube of side 1 at the
    origin. Image i has id 100 + i and is named frame_{n - 1 - i}.png: written in reverse order of
    names."""
    cameras = [Camera(i + 1, m, W, H, list(CAMERA_MODELS[m][0])) for i, m in enumerate(models)]
    images = []
    for i, c in enumerate(centres(n)):
        r_c2w = look_at(c, WORLD_UP)
        r_w2c = r_c2w.T
        images.append(
            Image(
                id=100 + i,
                qvec=qvec_of(r_w2c),
                tvec=(-r_w2c @ c).tolist(),
                camera_id=cameras[i % len(cameras)].id,
                name=f"frame_{n - 1 - i:05d}.png",
                points2d=[(1.5, 2.5, 0), (3.25, 4.75, -1)],
                rotation=r_w2c,
            )
        )
    xyz = np.random.default_rng(0).uniform(-0.5, 0.5, (points, 3)).tolist()
    return Model(cameras, images, xyz)


def write_bin(folder: Path, model: Model) -> None:
    cameras = struct.pack("<Q", len(model.cameras))
    for c in model.cameras:
        cameras += struct.pack("<IiQQ", c.id, MODEL_IDS[c.model], c.width, c.height)
        cameras += struct.pack(f"<{len(c.params)}d", *c.params)
    images = struct.pack("<Q", len(model.images))
    for im in model.images:
        images += struct.pack("<I7dI", im.id, *im.qvec, *im.tvec, im.camera_id)
        images += im.name.encode() + b"\0" + struct.pack("<Q", len(im.points2d))
        images += b"".join(struct.pack("<ddq", *p) for p in im.points2d)
    points = struct.pack("<Q", len(model.points))
    for i, xyz in enumerate(model.points):
        points += struct.pack("<Q3d3BdQ", i, *xyz, 200, 100, 50, 0.5, 2)
        points += struct.pack("<4i", model.images[0].id, 0, model.images[1].id, 0)
    (folder / "cameras.bin").write_bytes(cameras)
    (folder / "images.bin").write_bytes(images)
    (folder / "points3D.bin").write_bytes(points)


def write_txt(folder: Path, model: Model) -> None:
    # repr: the same float64 values as the binary model's
    cameras = [
        "# Camera list with one line of data per camera:",
        f"# Number of cameras: {len(model.cameras)}",
    ]
    cameras += [
        f"{c.id} {c.model} {c.width} {c.height} " + " ".join(map(repr, c.params))
        for c in model.cameras
    ]
    images = [
        "# Image list with two lines of data per image:",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
    ]
    for im in model.images:
        images.append(
            " ".join(map(repr, [im.id, *im.qvec, *im.tvec, im.camera_id])) + f" {im.name}"
        )
        images.append(" ".join(f"{x!r} {y!r} {p}" for x, y, p in im.points2d))
    points = ["# 3D point list with one line of data per point:"]
    a, b = model.images[0].id, model.images[1].id
    points += [
        f"{i} {x!r} {y!r} {z!r} 200 100 50 0.5 {a} 0 {b} 0"
        for i, (x, y, z) in enumerate(model.points)
    ]
    for name, lines in (("cameras", cameras), ("images", images), ("points3D", points)):
        (folder / f"{name}.txt").write_text("\n".join(lines) + "\n")


def write_scene(root: Path, model: Model, form: str = "bin") -> Path:
    """sparse/0/ in `form` and images/ with one 8x6 PNG (of its camera's size) per registered
    image."""
    (root / "sparse" / "0").mkdir(parents=True, exist_ok=True)
    (write_bin if form == "bin" else write_txt)(root / "sparse" / "0", model)
    sizes = {c.id: (c.width, c.height) for c in model.cameras}
    for i, im in enumerate(model.images):
        w, h = sizes.get(im.camera_id, (W, H))
        path = root / "images" / im.name
        path.parent.mkdir(parents=True, exist_ok=True)
        pixels = torch.full((h, w, 3), 20 * i, dtype=torch.uint8)
        pixels[..., 1] = torch.arange(w, dtype=torch.uint8) * 30
        save_png(pixels, path)
    return root


@pytest.fixture(params=["bin", "txt"])
def form(request) -> str:
    return request.param


@pytest.fixture
def colmap(tmp_path, form) -> Path:
    return write_scene(tmp_path / "colmap", tiny_model(), form)


def views_by_name(scene) -> dict:
    """name -> (intrinsics, distortion, c2w) of every view, whatever its split."""
    out = {}
    for views in scene.splits.values():
        for i, name in enumerate(views.names):
            cams = views.cameras
            out[name] = (cams.intrinsics[i], cams.distortion[i], cams.c2w[i])
    return out


# --- what loads -----------------------------------------------------------------------------------


def test_every_camera_model_loads_as_written(tmp_path, form):
    model = tiny_model(models=tuple(CAMERA_MODELS))
    scene = load_scene(write_scene(tmp_path / "c", model, form))
    assert scene.format == "colmap"
    assert scene.extras["camera_models"] == sorted(CAMERA_MODELS)
    loaded = views_by_name(scene)
    for im in model.images:
        cam = model.cameras[im.camera_id - 1]
        _, intrinsics, distortion = CAMERA_MODELS[cam.model]
        got_intrinsics, got_distortion, _ = loaded[Path(im.name).stem]
        assert got_intrinsics.tolist() == pytest.approx(intrinsics, rel=1e-6), cam.model
        assert got_distortion.tolist() == pytest.approx(distortion, rel=1e-6, abs=1e-9), cam.model


def test_centres_and_directions_are_the_ones_written(colmap):
    """World centre = (axes @ (-R^T t) - origin) / scale, viewing direction = axes @ R^T z; and
    what normalisation keeps: ratios of distances between centres, angles between directions."""
    scene = load_scene(colmap)
    norm = scene.normalization
    axes = norm.axes.double()
    loaded = views_by_name(scene)
    expected_centres, expected_forward, got_centres, got_forward = [], [], [], []
    for im in tiny_model().images:
        r_w2c = torch.tensor(im.rotation)
        centre = -r_w2c.T @ torch.tensor(im.tvec, dtype=torch.float64)
        forward = r_w2c.T @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        down = r_w2c.T @ torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
        c2w = loaded[Path(im.name).stem][2].double()
        world = (axes @ centre - norm.origin.double()) / norm.scale
        assert torch.allclose(c2w[:, 3], world, atol=1e-5)
        assert torch.allclose(-c2w[:, 2], axes @ forward, atol=1e-5)
        assert torch.allclose(c2w[:, 1], -(axes @ down), atol=1e-5)  # OpenGL up = -OpenCV y
        expected_centres.append(centre)
        expected_forward.append(forward)
        got_centres.append(c2w[:, 3])
        got_forward.append(-c2w[:, 2])
    e, g = torch.stack(expected_centres), torch.stack(got_centres)
    de, dg = torch.cdist(e, e), torch.cdist(g, g)
    assert torch.allclose(dg * norm.scale, de, atol=1e-5)
    assert torch.allclose(dg / dg.max(), de / de.max(), atol=1e-6)
    fe, fg = torch.stack(expected_forward), torch.stack(got_forward)
    assert torch.allclose(fg @ fg.T, fe @ fe.T, atol=1e-5)
    # the world is z up: the cameras' mean up vector (-WORLD_UP here) is rotated onto +z
    up = torch.stack([v[2][:, 1].double() for v in loaded.values()]).mean(0)
    assert torch.allclose(
        up / up.norm(), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), atol=1e-6
    )


def llff_of(root: Path, model: Model) -> Path:
    """The same cameras, images and points as an LLFF capture (poses_bounds.npy rows: [down, right,
    back, centre, hwf], near, far)."""
    (root / "sparse" / "0").mkdir(parents=True)
    write_bin(root / "sparse" / "0", model)
    (root / "sparse" / "0" / "cameras.bin").unlink()
    (root / "sparse" / "0" / "images.bin").unlink()
    rows = []
    for im in sorted(model.images, key=lambda im: im.name):
        r_c2w = im.rotation.T
        centre = -r_c2w @ np.array(im.tvec)
        pose = np.stack([r_c2w[:, 1], r_c2w[:, 0], -r_c2w[:, 2], centre, [H, W, 8.0]], 1)
        rows.append(np.concatenate([pose.reshape(-1), [1.0, 8.0]]))
    np.save(root / "poses_bounds.npy", np.array(rows))
    for i, im in enumerate(model.images):
        (root / "images").mkdir(exist_ok=True)
        save_png(torch.full((H, W, 3), 20 * i, dtype=torch.uint8), root / "images" / im.name)
    return root


def test_the_same_cameras_as_an_llff_capture_load_to_the_same_scene(tmp_path, form):
    model = tiny_model(models=("SIMPLE_PINHOLE",))  # f 8, principal point at the centre: LLFF's
    colmap = load_scene(write_scene(tmp_path / "colmap", model, form))
    llff = load_scene(llff_of(tmp_path / "llff", model))
    assert llff.format == "llff" and llff.bounds.source == "sparse_points"
    for split in ("train", "val"):
        a, b = colmap.splits[split], llff.splits[split]
        assert a.names == b.names
        assert torch.allclose(a.cameras.c2w, b.cameras.c2w, atol=1e-5)
        assert torch.allclose(a.cameras.intrinsics, b.cameras.intrinsics)
    assert torch.allclose(colmap.bounds.aabb, llff.bounds.aabb, atol=1e-5)
    assert colmap.normalization.scale == pytest.approx(llff.normalization.scale, rel=1e-6)


def test_binary_and_text_load_to_identical_scenes(tmp_path):
    model = tiny_model(models=tuple(CAMERA_MODELS))
    a = load_scene(write_scene(tmp_path / "bin", model, "bin"))
    b = load_scene(write_scene(tmp_path / "txt", model, "txt"))
    assert a.extras["colmap_model"] == "sparse/0 (binary)"
    assert b.extras["colmap_model"] == "sparse/0 (text)"
    assert a.splits.keys() == b.splits.keys()
    for name in a.splits:
        va, vb = a.splits[name], b.splits[name]
        assert va.names == vb.names
        for f in ("intrinsics", "c2w", "width", "height", "distortion"):
            assert torch.equal(getattr(va.cameras, f), getattr(vb.cameras, f)), f
    assert torch.equal(a.bounds.aabb, b.bounds.aabb) and torch.equal(a.points, b.points)
    assert torch.equal(a.normalization.axes, b.normalization.axes)


def test_every_8th_image_by_sorted_name_is_val(colmap):
    scene = load_scene(colmap)
    names = [f"frame_{i:05d}" for i in range(10)]
    assert scene.splits["val"].names == [names[0], names[8]]
    assert scene.train.names == [n for i, n in enumerate(names) if i % 8]


def test_downscale_resizes_images_and_intrinsics(colmap):
    scene = load_scene(colmap, downscale=2)
    cams = scene.train.cameras
    assert scene.downscale == 2 and scene.train.images[0].shape == (3, 4, 3)
    assert cams.width.unique().tolist() == [4] and cams.height.unique().tolist() == [3]
    assert cams.intrinsics[0].tolist() == pytest.approx([8.5 / 2, 7.5 / 2, 4.25 / 2, 2.75 / 2])


def test_the_sparse_points_set_the_bounds(colmap, form):
    scene = load_scene(colmap)
    assert scene.bounds.source == "sparse_points" and len(scene.points) == 40
    assert 0 < scene.bounds.num_points <= 40
    lo, hi = scene.bounds.aabb
    inside = ((scene.points >= lo) & (scene.points <= hi)).all(dim=1)
    assert inside.float().mean() >= 0.95
    assert float((hi - lo).max()) == pytest.approx(2.0)  # the box's longest side spans [-1, 1]
    (colmap / "sparse" / "0" / f"points3D.{form}").unlink()
    assert load_scene(colmap).bounds.source == "camera_axes"


def test_names_may_hold_subfolders(tmp_path, form):
    model = tiny_model(n=3).edit_image(1, name="left/frame_b.png")
    scene = load_scene(write_scene(tmp_path / "c", model, form))
    assert "left_frame_b" in scene.train.names


# --- detection ------------------------------------------------------------------------------------


def test_a_colmap_folder_is_detected(colmap):
    assert detect_format(colmap) == "colmap"


def test_cameras_without_images_is_no_colmap_model(tmp_path):
    root = write_scene(tmp_path / "c", tiny_model(n=3))
    (root / "sparse" / "0" / "images.bin").unlink()
    with pytest.raises(SceneError, match=r"sparse/0/cameras.bin \+ sparse/0/images.bin \(colmap\)"):
        detect_format(root)


def test_an_llff_capture_with_its_colmap_model_stays_llff(colmap):
    (colmap / "poses_bounds.npy").write_bytes(b"")
    assert detect_format(colmap) == "llff"


def test_fern_stays_llff(fern_dir):
    """fern keeps sparse/0/cameras.bin (without images.bin) beside poses_bounds.npy."""
    assert (fern_dir / "sparse" / "0" / "cameras.bin").is_file()
    assert detect_format(fern_dir) == "llff"


# --- what is refused ------------------------------------------------------------------------------


def write(root: Path, name: str, data: bytes) -> None:
    (root / "sparse" / "0" / name).write_bytes(data)


def read(root: Path, name: str) -> bytes:
    return (root / "sparse" / "0" / name).read_bytes()


SUPPORTED = "use one of SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV"


@pytest.mark.parametrize("model", ["OPENCV_FISHEYE", "FOV"])
def test_an_unsupported_camera_model_is_named(tmp_path, form, model):
    bad = tiny_model(n=3)
    bad.cameras[0] = replace(bad.cameras[0], model=model, params=[8.0] * 8)
    root = write_scene(tmp_path / "c", bad, form)
    shown = f"{model} \\(id {MODEL_IDS[model]}\\)" if form == "bin" else model
    error = expect(root, f"camera 1 has model {shown}, which is not supported", f"cameras.{form}")
    assert SUPPORTED in error.problem


def test_an_unknown_model_id_is_named(tmp_path):
    root = write_scene(tmp_path / "c", tiny_model(n=3))
    data = bytearray(read(root, "cameras.bin"))
    data[12:16] = struct.pack("<i", 42)
    write(root, "cameras.bin", bytes(data))
    expect(root, r"camera 1 has model unknown \(id 42\), which is not supported", "cameras.bin")


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
def test_truncated_binary_files(tmp_path, name):
    root = write_scene(tmp_path / "c", tiny_model(n=3))
    write(root, name, read(root, name)[:-5])
    expect(root, f"truncated or malformed COLMAP {name}", name)


@pytest.mark.parametrize(
    "name, what", [("cameras.bin", "cameras"), ("images.bin", "images"), ("points3D.bin", "points")]
)
def test_a_count_larger_than_the_bytes_present(tmp_path, name, what):
    root = write_scene(tmp_path / "c", tiny_model(n=3))
    write(root, name, struct.pack("<Q", 10**6) + read(root, name)[8:])
    expect(root, f"COLMAP {name} claims 1,000,000 {what} but holds", name)


def test_trailing_bytes(tmp_path):
    root = write_scene(tmp_path / "c", tiny_model(n=3))
    write(root, "cameras.bin", read(root, "cameras.bin") + b"\0\0\0")
    expect(root, "malformed COLMAP cameras.bin: 3 trailing bytes", "cameras.bin")


def test_a_missing_image_file(colmap, form):
    (colmap / "images" / "frame_00002.png").unlink()
    expect(colmap, rf"image is missing \(image \d+ in images.{form}\)", "frame_00002.png")


def test_an_image_naming_a_missing_camera(tmp_path, form):
    root = write_scene(tmp_path / "c", tiny_model(n=3).edit_image(1, camera_id=7), form)
    expect(
        root,
        f"image 101 'frame_00001.png' names camera 7, which cameras.{form} does not hold",
        f"images.{form}",
    )


def test_an_image_of_another_size_than_its_camera(colmap, form):
    save_png(torch.zeros(6, 9, 3, dtype=torch.uint8), colmap / "images" / "frame_00004.png")
    expect(
        colmap,
        rf"image is 9x6 pixels but camera 1 in cameras.{form} says 8x6 "
        rf"\(image \d+ in images.{form}\)",
        "frame_00004.png",
    )


@pytest.mark.parametrize("vector, index", [("qvec", 2), ("tvec", 0)])
def test_nan_in_a_pose(tmp_path, form, vector, index):
    model = tiny_model(n=3)
    values = list(getattr(model.images[0], vector))
    values[index] = float("nan")
    root = write_scene(tmp_path / "c", model.edit_image(0, **{vector: values}), form)
    expect(
        root,
        rf"{vector} \(image 100 'frame_00002.png'\) has non-finite values",
        f"images.{form}",
    )


def test_a_quaternion_that_is_not_a_rotation(tmp_path, form):
    root = write_scene(tmp_path / "c", tiny_model(n=3).edit_image(2, qvec=[0.5, 0, 0, 0]), form)
    expect(
        root,
        r"qvec \(image 102 'frame_00000.png'\) must be a unit quaternion.*norm is 0.5",
        f"images.{form}",
    )


def test_a_name_leading_out_of_the_scene(tmp_path, form):
    model = tiny_model(n=3).edit_image(0, name="../../elsewhere.png")
    root = tmp_path / "scene"
    write_scene(root, model, form)
    expect(root, r"image name \(image 100 '../../elsewhere.png'\) points outside", f"images.{form}")


def test_duplicate_ids_and_names(tmp_path, form):
    model = tiny_model(n=3)
    twice = replace(model, cameras=model.cameras * 2)
    expect(write_scene(tmp_path / "a", twice, form), "camera id 1 appears twice", f"cameras.{form}")
    same = model.edit_image(1, name=model.images[0].name)
    expect(
        write_scene(tmp_path / "b", same, form),
        "images 10[01] and 10[01] have the same name",
        f"images.{form}",
    )


def test_no_images_folder(tmp_path, form):
    root = write_scene(tmp_path / "c", tiny_model(n=3), form)
    for p in sorted((root / "images").iterdir()):
        p.unlink()
    (root / "images").rmdir()
    expect(root, "no images/ folder beside sparse/0", "c")


def test_wrong_number_of_parameters(tmp_path):
    model = tiny_model(n=3)
    model.cameras[0] = replace(model.cameras[0], params=[8.0, 8.0, 4.0])
    root = write_scene(tmp_path / "c", model, "txt")
    expect(
        root, r"camera 1 \(PINHOLE\) must have 4 parameters \(fx fy cx cy\), got 3", "cameras.txt"
    )


TEXT_CASES = {  # file, line (1-based, comments counted) -> its replacement, what is said
    "a camera of 3 fields": (
        "cameras.txt",
        3,
        "1 PINHOLE 8",
        r"line 3 has 3 field\(s\), not CAMERA_ID",
    ),
    "an image of 9 fields": (
        "images.txt",
        3,
        "100 1 0 0 0 0 0 4 1",
        r"line 3 has 9 field\(s\), not IMAGE_ID QW",
    ),
    "a point of 5 fields": ("points3D.txt", 2, "0 1.0 2.0 3.0 200", r"line 2 has 5 field\(s\)"),
    "a width that is not a number": (
        "cameras.txt",
        3,
        "1 PINHOLE eight 6 8 8 4 3",
        "WIDTH on line 3 is not a whole number",
    ),
    "a focal length of 1e400": (
        "cameras.txt",
        3,
        "1 PINHOLE 8 6 1e400 8 4 3",
        "parameter fx of camera 1 must be finite",
    ),
    "a pose that is not numbers": (
        "images.txt",
        3,
        "100 1 0 0 zero 0 0 4 1 frame_00000.png",
        "the pose of image 100 on line 3 are not numbers",
    ),
    "a POINTS2D line of pairs": (
        "images.txt",
        4,
        "1.0 2.0 3.0 4.0",
        r"POINTS2D line of image 100 \(line 4\) must hold \(X, Y, POINT3D_ID\) triples",
    ),
    "a point at NaN": (
        "points3D.txt",
        2,
        "0 nan 2.0 3.0 200 100 50 0.5 1 0",
        "COLMAP points: 1 are non-finite",
    ),
}


@pytest.mark.parametrize("case", TEXT_CASES)
def test_text_lines_are_parsed_strictly(tmp_path, case):
    name, number, line, match = TEXT_CASES[case]
    root = write_scene(tmp_path / "c", tiny_model(n=3), "txt")
    lines = (root / "sparse" / "0" / name).read_text().split("\n")
    lines[number - 1] = line
    (root / "sparse" / "0" / name).write_text("\n".join(lines))
    expect(root, match, name)


def test_images_txt_needs_its_points2d_lines(tmp_path):
    root = write_scene(tmp_path / "c", tiny_model(n=3), "txt")
    path = root / "sparse" / "0" / "images.txt"
    lines = path.read_text().split("\n")
    # one line an image: the second image's line is read as the first one's POINTS2D
    path.write_text("\n".join(lines[:2] + lines[2:-1:2]) + "\n")
    expect(root, r"POINTS2D line of image 100 \(line 4\) must hold", "images.txt")
    # the last image without its POINTS2D line
    path.write_text("\n".join(lines[:-2]) + "\n")
    expect(root, r"image 102 \(line 7\) has no POINTS2D line after it", "images.txt")


# --- a georeferenced model (`leco scene poses` with GPS) ------------------------------------------


def test_a_georeferenced_model_keeps_its_east_north_up_metres(tmp_path, form):
    """With georeference.json the model's frame is already z up in metres: no camera-up rotation,
    and the scene says metres and where its origin lies."""
    root = write_scene(tmp_path / "geo", tiny_model(), form)
    origin = {"latitude": 47.3769, "longitude": 8.5417, "altitude": 408.0}
    (root / "georeference.json").write_text(
        json.dumps({"frame": "ENU", "units": "metres", "origin": origin, "scale": 1.0})
    )
    scene = load_scene(root)
    assert scene.normalization.units == "metres"
    assert torch.equal(scene.normalization.axes, torch.eye(3))
    assert scene.extras["georeference"] == {"frame": "ENU", "origin": origin}
    plain = load_scene(write_scene(tmp_path / "plain", tiny_model(), form))
    assert plain.normalization.units == "source units"
    assert not torch.equal(plain.normalization.axes, torch.eye(3))


@pytest.mark.parametrize(
    "content, problem",
    [
        ('{"frame": "ECEF", "units": "metres"}', "expected"),
        ('{"frame": "ENU", "units": "metres", "origin": {"latitude": "north"}}', "origin"),
        ("[1, 2", "JSON"),
    ],
)
def test_a_broken_georeference_is_named(tmp_path, content, problem):
    root = write_scene(tmp_path / "geo", tiny_model())
    (root / "georeference.json").write_text(content)
    with pytest.raises(SceneError, match=problem) as info:
        load_scene(root)
    assert "georeference.json" in str(info.value)

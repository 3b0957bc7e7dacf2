"""The nerfstudio reader, on a transforms.json built from real lego frames: intrinsics, splits,
distortion (applied, not ignored) and sparse points."""

import json
import math
import shutil
import struct

import pytest
import torch

from model.scenes import SceneError, load_scene, pixel_rays
from model.scenes.cameras import make_cameras

FOCAL = 0.5 * 200 / math.tan(0.5 * 0.6911112070083618)


@pytest.fixture
def nerfstudio(tmp_path, lego_dir):
    root = tmp_path / "ns"
    (root / "images").mkdir(parents=True)
    data = json.loads((lego_dir / "transforms_train.json").read_text())
    frames = []
    for f in data["frames"][:9]:
        name = f["file_path"].split("/")[-1] + ".png"
        shutil.copy(lego_dir / "train" / name, root / "images" / name)
        frames.append({"file_path": f"images/{name}", "transform_matrix": f["transform_matrix"]})
    transforms = {
        "camera_model": "OPENCV",
        "fl_x": FOCAL,
        "fl_y": FOCAL,
        "cx": 100.0,
        "cy": 100.0,
        "w": 200,
        "h": 200,
        "frames": frames,
    }
    (root / "transforms.json").write_text(json.dumps(transforms))
    return root


def rewrite(root, fn):
    data = json.loads((root / "transforms.json").read_text())
    fn(data)
    (root / "transforms.json").write_text(json.dumps(data))


def test_cameras_intrinsics_and_downscale(nerfstudio):
    scene = load_scene(nerfstudio)
    assert scene.format == "nerfstudio"
    # every 8th frame is val
    assert {k: len(v) for k, v in scene.splits.items()} == {"train": 7, "val": 2}
    cams = scene.train.cameras
    assert torch.allclose(cams.intrinsics[0], torch.tensor([FOCAL, FOCAL, 100.0, 100.0]))
    half = load_scene(nerfstudio, downscale=2)
    assert half.train.images[0].shape == (100, 100, 3)
    assert torch.allclose(
        half.train.cameras.intrinsics[0], torch.tensor([FOCAL / 2, FOCAL / 2, 50.0, 50.0])
    )


def test_per_frame_intrinsics_override_global(nerfstudio):
    rewrite(nerfstudio, lambda d: d["frames"][1].update({"fl_x": 300.0, "fl_y": 310.0}))
    scene = load_scene(nerfstudio)
    index = scene.train.names.index("r_1")
    assert scene.train.cameras.intrinsics[index, :2].tolist() == [300.0, 310.0]
    assert scene.train.cameras.intrinsics[scene.train.names.index("r_2"), 0] == pytest.approx(FOCAL)


def test_split_lists_decide_the_split(nerfstudio):
    def lists(d):
        names = [f["file_path"] for f in d["frames"]]
        d["train_filenames"], d["val_filenames"] = names[:5], names[5:8]

    rewrite(nerfstudio, lists)
    scene = load_scene(nerfstudio)
    # the 9th frame is in no list: unused
    assert len(scene.train) == 5 and len(scene.splits["val"]) == 3


def distort(x, y, k1, k2, p1, p2):
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    return x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (
        r2 + 2 * y * y
    ) + 2 * p2 * x * y


def test_opencv_distortion_is_applied(nerfstudio):
    k = dict(k1=-0.1, k2=0.01, p1=1e-3, p2=-1e-3)
    rewrite(nerfstudio, lambda d: d.update(k))
    scene = load_scene(nerfstudio)
    cams = scene.train.cameras
    assert cams.distortion[0].tolist() == pytest.approx([-0.1, 0.01, 1e-3, -1e-3])
    # Known camera-frame directions -> ideal image coordinates -> distorted pixels.
    g = torch.Generator().manual_seed(0)
    x, y = (
        (torch.rand(200, generator=g, dtype=torch.float64) - 0.5) * 0.7,
        (torch.rand(200, generator=g, dtype=torch.float64) - 0.5) * 0.7,
    )
    xd, yd = distort(x, y, **k)
    u, v = xd * FOCAL + 100 - 0.5, yd * FOCAL + 100 - 0.5
    cam = torch.zeros(200, dtype=torch.long)
    _, d = pixel_rays(cams, cam, u.float(), v.float())
    expected = torch.stack([x, -y, -torch.ones_like(x)], -1)
    expected = (expected / expected.norm(dim=-1, keepdim=True)).float() @ cams.c2w[0, :, :3].T
    angle = lambda a, b: torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1))
    assert angle(d, expected).max() < 1e-5
    pinhole = make_cameras(cams.intrinsics[:1], cams.c2w[:1], cams.width[:1], cams.height[:1])
    _, d_pinhole = pixel_rays(pinhole, cam, u.float(), v.float())
    # over a pixel at this focal: ignoring it would show
    assert angle(d_pinhole, expected).max() > 4e-3


def test_unsupported_models_are_refused(nerfstudio):
    rewrite(nerfstudio, lambda d: d.update(camera_model="OPENCV_FISHEYE"))
    with pytest.raises(
        SceneError, match=r"camera_model 'OPENCV_FISHEYE' \(frame 0\) is not supported"
    ):
        load_scene(nerfstudio)
    rewrite(nerfstudio, lambda d: d.update(camera_model="OPENCV", k3=0.02))
    with pytest.raises(SceneError, match="distortion term k3 .* is not supported"):
        load_scene(nerfstudio)


def test_missing_image_and_field(nerfstudio):
    (nerfstudio / "images" / "r_3.png").unlink()
    with pytest.raises(
        SceneError, match=r"r_3.png: image is missing \(listed in transforms.json \(frame 3\)\)"
    ):
        load_scene(nerfstudio)
    rewrite(nerfstudio, lambda d: d.pop("fl_x"))
    with pytest.raises(SceneError, match=r"missing field 'fl_x' \(frame 0\)"):
        load_scene(nerfstudio)


@pytest.mark.parametrize("binary", [True, False])
def test_sparse_points_from_ply(nerfstudio, binary):
    g = torch.Generator().manual_seed(1)
    points = (torch.rand(500, 3, generator=g) - 0.5) * 2.0  # the lego volume
    header = [
        "ply",
        f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
        "element vertex 500",
        "property float x",
        "property float y",
        "property float z",
        "property uchar red",
        "property uchar green",
        "property uchar blue",
        "end_header",
    ]
    body = (
        b"".join(struct.pack("<3f3B", *p.tolist(), 10, 20, 30) for p in points)
        if binary
        else "".join(f"{a} {b} {c} 10 20 30\n" for a, b, c in points.tolist()).encode()
    )
    (nerfstudio / "sparse_pc.ply").write_bytes(("\n".join(header) + "\n").encode() + body)
    rewrite(nerfstudio, lambda d: d.update(ply_file_path="sparse_pc.ply"))
    scene = load_scene(nerfstudio)
    assert scene.bounds.source == "sparse_points" and len(scene.points) == 500


@pytest.mark.parametrize("field", ["file_path", "ply_file_path"])
def test_paths_outside_the_scene_are_refused_alike_whether_they_exist(nerfstudio, tmp_path, field):
    """A named path that is absolute or climbs out is refused before it is opened, and the answer
    does not tell whether the target exists."""
    (tmp_path / "other").mkdir()
    shutil.copy(nerfstudio / "images" / "r_0.png", tmp_path / "other" / "stolen.png")
    messages = []
    for target in (
        "/proc/self/environ",
        "../other/stolen.png",
        "../other/absent.png",
        "images/../../ns/../x",
    ):
        if field == "file_path":
            rewrite(nerfstudio, lambda d, target=target: d["frames"][0].update(file_path=target))
        else:
            rewrite(nerfstudio, lambda d, target=target: d.update(ply_file_path=target))
        with pytest.raises(SceneError) as info:
            load_scene(nerfstudio)
        assert info.value.path.name == "transforms.json"
        where = " (frame 0)" if field == "file_path" else ""
        assert info.value.problem == f"{field}{where} {target!r} points outside the scene folder"
        messages.append(info.value.problem.replace(repr(target), "X"))
    assert len(set(messages)) == 1  # existing, missing and unreadable targets answer the same


def test_a_symlink_out_of_the_scene_is_refused_and_one_inside_is_followed(nerfstudio, tmp_path):
    outside = tmp_path / "secret.png"
    shutil.copy(nerfstudio / "images" / "r_1.png", outside)
    (nerfstudio / "images" / "r_1.png").unlink()
    (nerfstudio / "images" / "r_1.png").symlink_to(outside)
    with pytest.raises(
        SceneError, match=r"file_path \(frame 1\) 'images/r_1.png' points outside the scene folder"
    ):
        load_scene(nerfstudio)
    (nerfstudio / "images" / "r_1.png").unlink()
    # inside: fine
    (nerfstudio / "images" / "r_1.png").symlink_to(nerfstudio / "images" / "r_2.png")
    assert len(load_scene(nerfstudio).train) > 0

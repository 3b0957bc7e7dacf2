"""Every broken dataset fails with a SceneError naming the file and the problem; loading writes
nothing."""

import json
import shutil

import numpy as np
import pytest
import torch
from PIL import Image

from model.scenes import SceneError, load_scene


def snapshot(folder):
    return {
        str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns)
        for p in sorted(folder.rglob("*"))
    }


def expect(root, match, file=None):
    before = snapshot(root) if root.exists() else None
    with pytest.raises(SceneError, match=match) as info:
        load_scene(root)
    if file is not None:
        assert str(info.value.path).endswith(file), f"{info.value.path} does not name {file}"
    if before is not None:
        assert snapshot(root) == before  # read-only, even on failure
    return info.value


# --- Blender
# -------------------------------------------------------------------------------------------------


@pytest.fixture
def blender(tmp_path, lego_dir):
    """Three lego train frames and one val frame, rewritten json."""
    root = tmp_path / "lego"
    (root / "train").mkdir(parents=True)
    (root / "val").mkdir()
    for split, names in (("train", ["r_0", "r_1", "r_2"]), ("val", ["r_0"])):
        data = json.loads((lego_dir / f"transforms_{split}.json").read_text())
        frames = [f for f in data["frames"] if f["file_path"].split("/")[-1] in names]
        for f in frames:
            shutil.copy(lego_dir / (f["file_path"] + ".png"), root / split)
        (root / f"transforms_{split}.json").write_text(json.dumps({**data, "frames": frames}))
    return root


def edit_json(path, fn):
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def test_blender_good_fixture_loads(blender):
    before = snapshot(blender)
    scene = load_scene(blender)
    assert len(scene.train) == 3 and snapshot(blender) == before


def test_blender_missing_image(blender):
    (blender / "train" / "r_1.png").unlink()
    expect(blender, "image is missing", "r_1")


def test_blender_unreadable_image(blender):
    (blender / "train" / "r_2.png").write_bytes(b"not a png at all")
    expect(blender, "image is unreadable", "r_2.png")


def png_claiming(width: int, height: int) -> bytes:
    """A real 1x1 PNG whose header (IHDR, CRC fixed) claims another size: a decompression bomb's
    header."""
    import io
    import struct
    import zlib

    buffer = io.BytesIO()
    Image.new("RGB", (1, 1)).save(buffer, "PNG")
    data = bytearray(buffer.getvalue())
    ihdr = data.index(b"IHDR")
    data[ihdr + 4 : ihdr + 12] = struct.pack(">II", width, height)
    data[ihdr + 17 : ihdr + 21] = struct.pack(">I", zlib.crc32(bytes(data[ihdr : ihdr + 17])))
    return bytes(data)


def test_blender_image_with_huge_dimensions_is_refused_before_decoding(blender):
    (blender / "train" / "r_1.png").write_bytes(png_claiming(12_000, 10_000))  # our limit
    expect(
        blender,
        "image claims 12000x10000 pixels, more pixels than the 100 megapixel limit",
        "r_1.png",
    )
    # PIL's guard, earlier
    (blender / "train" / "r_1.png").write_bytes(png_claiming(60_000, 60_000))
    expect(blender, "image claims more pixels than the 100 megapixel limit", "r_1.png")


def test_blender_truncated_image(blender):
    data = (blender / "train" / "r_2.png").read_bytes()
    (blender / "train" / "r_2.png").write_bytes(data[: len(data) // 2])
    expect(blender, "image is unreadable", "r_2.png")


def test_blender_image_size_mismatch(blender):
    Image.new("RGBA", (100, 80)).save(blender / "train" / "r_1.png")
    expect(blender, "image is 100x80 pixels but its camera says 200x200", "r_1.png")


def test_blender_nan_pose(blender):
    edit_json(
        blender / "transforms_train.json",
        lambda d: d["frames"][1]["transform_matrix"][0].__setitem__(3, float("nan")),
    )
    expect(blender, r"camera pose \(frame 1\) has non-finite values", "transforms_train.json")


def test_blender_non_rigid_pose(blender):
    def shear(d):
        m = d["frames"][2]["transform_matrix"]
        m[0][1] += 0.3

    edit_json(blender / "transforms_train.json", shear)
    expect(blender, r"camera pose \(frame 2\) is not rigid", "transforms_train.json")


def test_blender_malformed_json(blender):
    (blender / "transforms_val.json").write_text('{"camera_angle_x": 0.69, "frames": [')
    expect(blender, "malformed JSON", "transforms_val.json")


def test_blender_missing_fields(blender):
    edit_json(blender / "transforms_train.json", lambda d: d.pop("camera_angle_x"))
    expect(blender, "missing field 'camera_angle_x'", "transforms_train.json")


def test_blender_missing_transform_matrix(blender):
    edit_json(blender / "transforms_train.json", lambda d: d["frames"][0].pop("transform_matrix"))
    expect(blender, r"missing field 'transform_matrix' \(frame 0\)", "transforms_train.json")


def test_blender_empty_split(blender):
    edit_json(blender / "transforms_val.json", lambda d: d.__setitem__("frames", []))
    expect(blender, "split has no frames", "transforms_val.json")


# --- Mega-NeRF
# -------------------------------------------------------------------------------------------------


def look_at_drb(position):
    """OpenGL c2w in Mega-NeRF's down-right-back frame, looking at the origin, 'up' = -x."""
    p = torch.tensor(position)
    forward = -p / p.norm()
    right = torch.linalg.cross(forward, torch.tensor([-1.0, 0.0, 0.0]))
    right = right / right.norm()
    up = torch.linalg.cross(right, forward)
    return torch.stack([right, up, -forward, p], dim=1)


@pytest.fixture
def meganerf(tmp_path):
    """Three views written by hand in the Mega-NeRF layout, aimed at one ground point."""
    root = tmp_path / "mega"
    torch.save(
        {"origin_drb": torch.zeros(3, dtype=torch.float64), "pose_scale_factor": 10.0},
        root.mkdir() or root / "coordinates.pt",
    )
    for split in ("train", "val"):
        (root / split / "metadata").mkdir(parents=True)
        (root / split / "rgbs").mkdir()
    positions = ([-1.0, 0.5, 0.0], [-1.0, -0.5, 0.0], [-1.0, 0.0, 0.5])  # 10 m up (x is down)
    for i, split in enumerate(("train", "train", "val")):
        c2w = look_at_drb(positions[i])
        torch.save(
            {"W": 16, "H": 12, "intrinsics": torch.tensor([20.0, 20.0, 8.0, 6.0]), "c2w": c2w},
            root / split / "metadata" / f"{i:06d}.pt",
        )
        Image.new("RGB", (16, 12), (i * 40, 90, 120)).save(root / split / "rgbs" / f"{i:06d}.png")
    return root


def test_meganerf_good_fixture_loads(meganerf):
    scene = load_scene(meganerf)
    assert scene.format == "meganerf" and len(scene.train) == 2 and len(scene.splits["val"]) == 1


def test_meganerf_parallel_cameras_without_geometry(meganerf):
    """Nadir cameras whose axes never cross, and no depth or points: the bounds cannot be found."""
    for path in sorted((meganerf / "train" / "metadata").glob("*.pt")) + [
        meganerf / "val/metadata/000002.pt"
    ]:
        meta = torch.load(path, weights_only=True)
        # looking down
        meta["c2w"][:, :3] = torch.tensor([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
        torch.save(meta, path)
    expect(meganerf, "cannot find the foreground: the cameras' optical axes never cross", "mega")


def test_meganerf_missing_image(meganerf):
    (meganerf / "train" / "rgbs" / "000001.png").unlink()
    expect(meganerf, "image is missing", "000001")


def test_meganerf_size_mismatch(meganerf):
    Image.new("RGB", (15, 12)).save(meganerf / "val" / "rgbs" / "000002.png")
    expect(meganerf, "image is 15x12 pixels but its camera says 16x12", "000002.png")


def test_meganerf_missing_metadata_field(meganerf):
    path = meganerf / "train" / "metadata" / "000000.pt"
    meta = torch.load(path, weights_only=True)
    del meta["c2w"]
    torch.save(meta, path)
    expect(meganerf, "metadata is missing field.*c2w", "000000.pt")


def test_meganerf_non_rigid_and_nan_pose(meganerf):
    path = meganerf / "train" / "metadata" / "000001.pt"
    meta = torch.load(path, weights_only=True)
    meta["c2w"][:, :3] *= 2.0
    torch.save(meta, path)
    expect(meganerf, "is not rigid", "000001.pt")
    meta["c2w"] = torch.full((3, 4), float("nan"))
    torch.save(meta, path)
    expect(meganerf, "non-finite", "000001.pt")


def test_meganerf_unreadable_metadata_and_coordinates(meganerf):
    (meganerf / "val" / "metadata" / "000002.pt").write_bytes(b"garbage")
    expect(meganerf, "cannot read this torch file", "000002.pt")
    torch.save({"origin_drb": torch.zeros(3)}, meganerf / "coordinates.pt")
    expect(meganerf, "'origin_drb' and 'pose_scale_factor'", "coordinates.pt")


def test_meganerf_empty_train_split(meganerf):
    for p in (meganerf / "train" / "metadata").iterdir():
        p.unlink()
    expect(meganerf, "the train split is empty", "metadata")


# --- LLFF
# -------------------------------------------------------------------------------------------------


@pytest.fixture
def llff(tmp_path, fern_dir):
    root = tmp_path / "fern"
    (root / "images_8").mkdir(parents=True)
    for i in range(9):
        shutil.copy(fern_dir / "images_8" / f"image{i:03d}.png", root / "images_8")
    np.save(root / "poses_bounds.npy", np.load(fern_dir / "poses_bounds.npy")[:9])
    return root


def test_llff_good_fixture_loads(llff):
    scene = load_scene(llff)
    # no sparse/ here: the per-image depth bounds are the evidence
    assert scene.bounds.source == "llff_bounds"
    assert len(scene.train) == 7 and len(scene.splits["val"]) == 2


def test_llff_image_count_mismatch(llff):
    (llff / "images_8" / "image004.png").unlink()
    expect(llff, "has 8 images but poses_bounds.npy has 9 poses", "images_8")


def test_llff_non_finite_and_bad_shape(llff):
    poses = np.load(llff / "poses_bounds.npy")
    poses[3, 3] = np.inf
    np.save(llff / "poses_bounds.npy", poses)
    expect(llff, r"non-finite values in row\(s\) \[3\]", "poses_bounds.npy")
    np.save(llff / "poses_bounds.npy", poses[:, :15])
    expect(llff, "must be an N x 17 array", "poses_bounds.npy")


def test_llff_non_rigid_pose(llff):
    poses = np.load(llff / "poses_bounds.npy")
    poses[5, :15] = (poses[5, :15].reshape(3, 5) * np.array([1.5, 1.5, 1.5, 1, 1])).reshape(-1)
    np.save(llff / "poses_bounds.npy", poses)
    expect(llff, r"camera pose \(row 5\) is not rigid", "poses_bounds.npy")


def test_llff_downscale_without_matching_folder(llff):
    with pytest.raises(
        SceneError, match="downscale 4 is not a multiple of any image folder's factor"
    ):
        load_scene(llff, downscale=4)


# --- detection
# -------------------------------------------------------------------------------------------------


def test_unknown_format_and_missing_path(tmp_path):
    (tmp_path / "photo.jpg").write_bytes(b"x")
    expect(tmp_path, r"unknown scene format.*found \['photo.jpg'\]")
    expect(tmp_path / "nope", "scene folder does not exist")
    with pytest.raises(SceneError, match="is not a folder"):
        load_scene(tmp_path / "photo.jpg")
    with pytest.raises(SceneError, match="downscale must be a positive integer"):
        load_scene(tmp_path, downscale=0)


# --- Paths that lead out of the scene folder
# -----------------------------------------------------------------


def test_blender_file_path_outside_the_scene(blender, tmp_path):
    shutil.copy(blender / "train" / "r_0.png", tmp_path / "elsewhere.png")
    for target in ("../elsewhere", str(tmp_path / "elsewhere"), "../nothing-here"):
        edit_json(
            blender / "transforms_train.json",
            lambda d, target=target: d["frames"][1].update(file_path=target),
        )
        error = expect(blender, "points outside the scene folder", "transforms_train.json")
        assert error.problem == f"file_path (frame 1) {target!r} points outside the scene folder"


def test_symlinks_out_of_the_scene_are_refused_in_every_format(blender, meganerf, llff, tmp_path):
    cases = [
        (blender, blender / "train" / "r_2.png"),
        (meganerf, meganerf / "train" / "rgbs" / "000001.png"),
        (meganerf, meganerf / "coordinates.pt"),
        (llff, llff / "images_8" / "image003.png"),
        (llff, llff / "poses_bounds.npy"),
    ]
    for i, (root, path) in enumerate(cases):
        outside = tmp_path / f"outside-{i}{path.suffix}"
        shutil.move(path, outside)
        path.symlink_to(outside)
        expect(root, "this file points outside the scene folder", path.name)
        path.unlink()
        shutil.move(outside, path)
        load_scene(root)  # and back inside, it loads


def test_a_jpeg_with_a_camera_trailer_is_read_and_a_cut_one_fails_when_decoded(tmp_path):
    """Cameras append data after a JPEG's end-of-image marker: the header check must not refuse it.
    A JPEG cut short passes the header check and is refused, naming the file, when its pixels are
    decoded."""
    from model.scenes.images import ImageFile, probe_image

    noise = np.random.default_rng(0).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    # noise: the data, not the header, fills the file
    Image.fromarray(noise).save(tmp_path / "a.jpg", quality=95)
    data = (tmp_path / "a.jpg").read_bytes()
    (tmp_path / "trailer.jpg").write_bytes(data + b"SEFH" + bytes(4096))
    assert probe_image(tmp_path / "trailer.jpg") == (64, 48)
    assert ImageFile(tmp_path / "trailer.jpg", 64, 48)().shape == (48, 64, 3)
    (tmp_path / "cut.jpg").write_bytes(data[: len(data) // 2])
    assert probe_image(tmp_path / "cut.jpg") == (64, 48)
    with pytest.raises(SceneError, match=r"cut\.jpg: image is unreadable"):
        ImageFile(tmp_path / "cut.jpg", 64, 48)()

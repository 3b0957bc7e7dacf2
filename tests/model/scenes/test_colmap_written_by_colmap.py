"""The COLMAP reader on models COLMAP itself writes (pycolmap), binary and text, for every camera
model it reads: the same intrinsics, distortion and camera centres as COLMAP holds, so the reader
and the test's own writer (test_colmap.py) cannot share a misreading of the format."""

import numpy as np
import pytest
import torch
from PIL import Image

from model.scenes import load_scene

pycolmap = pytest.importorskip("pycolmap")

W, H = 16, 12
PARAMS = {  # COLMAP's parameter order; the reader's (fx, fy, cx, cy) and (k1, k2, p1, p2)
    "SIMPLE_PINHOLE": ([14.0, 8.1, 5.9], [14.0, 14.0, 8.1, 5.9], [0, 0, 0, 0]),
    "PINHOLE": ([14.0, 15.0, 8.1, 5.9], [14.0, 15.0, 8.1, 5.9], [0, 0, 0, 0]),
    "SIMPLE_RADIAL": ([14.0, 8.1, 5.9, 0.05], [14.0, 14.0, 8.1, 5.9], [0.05, 0, 0, 0]),
    "RADIAL": ([14.0, 8.1, 5.9, 0.05, -0.01], [14.0, 14.0, 8.1, 5.9], [0.05, -0.01, 0, 0]),
    "OPENCV": (
        [14.0, 15.0, 8.1, 5.9, 0.05, -0.01, 0.001, -0.002],
        [14.0, 15.0, 8.1, 5.9],
        [0.05, -0.01, 0.001, -0.002],
    ),
}


def colmap_model(root, model: str, form: str, views: int = 9):
    """A model of `views` cameras on a ring looking inwards, written by pycolmap, with images."""
    rec = pycolmap.Reconstruction()
    camera = pycolmap.Camera.create_from_model_name(1, model, 14.0, W, H)
    camera.params = PARAMS[model][0]
    rec.add_camera_with_trivial_rig(camera)
    (root / "images").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(views):
        angle = 2 * np.pi * i / views
        centre = np.array([4 * np.cos(angle), 4 * np.sin(angle), 1.0 + 0.1 * i])
        forward = -centre / np.linalg.norm(centre)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        r_w2c = np.stack([right, down, forward])  # OpenCV camera axes as rows
        pose = pycolmap.Rigid3d(np.hstack([r_w2c, (-r_w2c @ centre)[:, None]]))
        image = pycolmap.Image(name=f"view_{i:02d}.png", camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, pose)
        pixels = (rng.random((H, W, 3)) * 255).astype(np.uint8)
        Image.fromarray(pixels).save(root / "images" / f"view_{i:02d}.png")
    (root / "sparse" / "0").mkdir(parents=True)
    (rec.write_binary if form == "bin" else rec.write_text)(str(root / "sparse" / "0"))
    return rec


@pytest.mark.parametrize("form", ["bin", "txt"])
@pytest.mark.parametrize("model", list(PARAMS))
def test_a_model_colmap_wrote_loads_as_colmap_holds_it(tmp_path, model, form):
    rec = colmap_model(tmp_path / "scene", model, form)
    scene = load_scene(tmp_path / "scene")
    assert scene.format == "colmap" and scene.extras["camera_models"] == [model]
    _, intrinsics, distortion = PARAMS[model]
    centres = {
        rec.image(i).name.removesuffix(".png"): rec.image(i).projection_center()
        for i in rec.reg_image_ids()
    }
    seen = 0
    for views in scene.splits.values():
        cams = views.cameras
        for k, name in enumerate(views.names):
            assert cams.intrinsics[k].tolist() == pytest.approx(intrinsics, rel=1e-6)
            assert cams.distortion[k].tolist() == pytest.approx(distortion, abs=1e-9)
            source = scene.normalization.to_source(cams.c2w[k][:, 3].double()[None])[0]
            assert source.numpy() == pytest.approx(centres[name], abs=1e-5)
            seen += 1
    assert seen == len(centres) == 9
    assert torch.isfinite(scene.bounds.aabb).all()

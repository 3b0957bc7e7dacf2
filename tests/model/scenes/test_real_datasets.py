"""The Blender and LLFF readers against the real scenes in ../shared/datasets (lego, fern)."""

import math

import pytest
import torch

from model.scenes import load_scene, pixel_rays
from model.scenes.formats.points import read_colmap_points

# camera_angle_x of the lego release
LEGO_FOCAL_200 = 0.5 * 200 / math.tan(0.5 * 0.6911112070083618)
FERN_FOCAL_8 = 3260.526333 / 8


@pytest.fixture(scope="module")
def lego(lego_dir):
    return load_scene(lego_dir)


@pytest.fixture(scope="module")
def fern(fern_dir):
    return load_scene(fern_dir)


def test_lego_cameras_and_intrinsics(lego):
    assert lego.format == "blender"
    assert {k: len(v) for k, v in lego.splits.items()} == {"train": 100, "val": 13, "test": 25}
    cams = lego.train.cameras
    assert cams.width.unique().tolist() == [200] and cams.height.unique().tolist() == [200]
    assert torch.allclose(cams.intrinsics[:, 0], torch.full((100,), LEGO_FOCAL_200), atol=1e-3)
    assert torch.allclose(cams.intrinsics[:, 2:], torch.full((100, 2), 100.0))
    # Appearance indices are unique across splits.
    all_idx = torch.cat([v.appearance for v in lego.splits.values()])
    assert len(all_idx.unique()) == 138


def test_lego_downscale_scales_intrinsics(lego_dir):
    small = load_scene(lego_dir, downscale=2)
    cams = small.train.cameras
    assert small.train.images[0].shape == (100, 100, 3)
    assert cams.width[0] == 100 and cams.height[0] == 100
    assert cams.intrinsics[0].tolist() == pytest.approx(
        [LEGO_FOCAL_200 / 2, LEGO_FOCAL_200 / 2, 50.0, 50.0], abs=1e-3
    )


def test_lego_cameras_look_at_the_origin(lego):
    """Every lego camera aims at the source origin: its principal ray passes through it."""
    target = lego.normalization.to_world(torch.zeros(1, 3)).float()[0]
    for views in lego.splits.values():
        cams = views.cameras
        n = len(cams)
        # The pixel whose centre is the principal point.
        o, d = pixel_rays(
            cams, torch.arange(n), cams.intrinsics[:, 2] - 0.5, cams.intrinsics[:, 3] - 0.5
        )
        assert torch.allclose(d, cams.forward, atol=1e-6)
        to_target = target - o
        miss = torch.linalg.cross(to_target, d).norm(dim=-1) / to_target.norm(dim=-1)
        # sine of the angle between the axis and the direction to the origin
        assert miss.max() < 1e-3


def test_lego_background_composited_white(lego, lego_dir):
    assert lego.train.images[0][0, 0].tolist() == [255, 255, 255]
    black = load_scene(lego_dir, background=(0.0, 0.0, 0.0))
    assert black.train.images[0][0, 0].tolist() == [0, 0, 0]


def test_lego_bounds_hold_the_model(lego):
    """Camera-only bounds: the axes converge on the origin; the box must hold the lego model
    (roughly |x|,|y| <= 1.2, z in [-0.4, 1.1] in source units) and exclude the cameras."""
    aabb_source = (
        lego.bounds.aabb.double() * lego.normalization.scale + lego.normalization.origin.double()
    )
    assert lego.bounds.source == "camera_axes"
    assert (aabb_source[0] <= torch.tensor([-1.2, -1.2, -0.4], dtype=torch.float64)).all()
    assert (aabb_source[1] >= torch.tensor([1.2, 1.2, 1.1], dtype=torch.float64)).all()
    inside = (
        (lego.train.cameras.centers >= lego.bounds.aabb[0])
        & (lego.train.cameras.centers <= lego.bounds.aabb[1])
    ).all(-1)
    assert not inside.any()


def test_fern_cameras_and_intrinsics(fern, fern_dir):
    assert fern.format == "llff" and fern.downscale == 8
    from model.scenes.info import describe

    # what the API checks a job's downscale against
    assert describe(fern)["image_folder_factors"] == [8]
    assert {k: len(v) for k, v in fern.splits.items()} == {"train": 17, "val": 3}
    assert fern.splits["val"].names == ["image000", "image008", "image016"]
    cams = fern.train.cameras
    assert (cams.width == 504).all() and (cams.height == 378).all()
    assert torch.allclose(cams.intrinsics[:, 0], torch.full((17,), FERN_FOCAL_8), atol=1e-2)
    half = load_scene(fern_dir, downscale=16)
    assert half.downscale == 16 and half.train.images[0].shape == (189, 252, 3)
    assert half.train.cameras.intrinsics[0, 0] == pytest.approx(FERN_FOCAL_8 / 2, abs=1e-2)


def test_fern_pose_convention_matches_sparse_points(fern, fern_dir):
    """COLMAP points lie in front of every camera, project inside its image, at LLFF's depth bounds:
    a wrong axis conversion puts them behind the camera or off the image."""
    points = fern.normalization.to_world(
        read_colmap_points(fern_dir / "sparse/0/points3D.bin")
    ).float()
    cams = fern.train.cameras
    for c in range(len(cams)):
        rel = points - cams.centers[c]
        r = cams.c2w[c, :, :3]
        x, y, z = (rel @ r).unbind(-1)  # camera frame: right, up, back
        depth = -z
        fx, fy, cx, cy = cams.intrinsics[c].tolist()
        u, v = fx * x / depth + cx, -fy * y / depth + cy
        visible = (depth > 0) & (u >= 0) & (u < 504) & (v >= 0) & (v < 378)
        assert visible.float().mean() > 0.9, (
            f"camera {c}: only {visible.float().mean():.2f} of points visible"
        )
    # Up alignment: the mean camera up vector is +z.
    up = cams.c2w[:, :, 1].mean(0)
    assert up[2] / up.norm() > 0.999


def test_fern_bounds_from_sparse_points(fern):
    assert fern.bounds.source == "sparse_points"
    inside = ((fern.points >= fern.bounds.aabb[0]) & (fern.points <= fern.bounds.aabb[1])).all(-1)
    assert inside.float().mean() > 0.97
    assert float((fern.bounds.aabb[1] - fern.bounds.aabb[0]).max()) == pytest.approx(2.0, abs=1e-4)

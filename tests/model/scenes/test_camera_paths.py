"""Camera paths: generated orbits, fly-overs and spirals are rigid poses that look where they
should; user paths convert from the dataset's frame to the world and back; what is not a camera is
refused by name."""

import json
import math

import pytest
import torch
from pydantic import ValidationError

from model.scenes.camera_paths import (
    PathError,
    fitting_distance,
    flyover,
    interpolate,
    look_at,
    orbit,
    source_to_world_pose,
    spiral,
    user_path,
    world_to_source_pose,
)
from model.scenes.cameras import pixel_rays, rotation_error
from model.scenes.scene import Normalization
from workers.render.schemas import MAX_VIDEO_PIXELS, RenderConfig, ViewRequest

AABB = torch.tensor([[-1.0, -0.8, -0.3], [1.0, 0.8, 0.3]])


def centre_ray(path, i):
    cams = path.cameras()
    o, d = pixel_rays(
        cams,
        torch.tensor([i]),
        torch.tensor([path.width / 2 - 0.5]),
        torch.tensor([path.height / 2 - 0.5]),
    )
    return o[0].double(), d[0].double()


def test_an_orbit_circles_the_box_at_its_pitch_and_looks_at_its_centre():
    path = orbit(AABB, 36, 64, 48, fov_deg=50, pitch_deg=30)
    assert len(path) == 36 and rotation_error(path.c2w).max() < 1e-9
    centres = path.c2w[:, :, 3]
    distance = centres.norm(dim=-1)
    assert torch.allclose(distance, distance[0].expand(36), atol=1e-9)
    pitch = torch.rad2deg(torch.asin(centres[:, 2] / distance))
    assert torch.allclose(pitch, torch.full((36,), 30.0, dtype=torch.float64), atol=1e-6)
    for i in (0, 9, 27):
        o, d = centre_ray(path, i)
        # distance of the centre ray from the box centre (the origin)
        miss = (o + d * (-(o @ d))).norm()
        assert miss < 1e-3
    # every corner of the box is in every frame (the default distance fits it)
    corners = torch.cartesian_prod(*[AABB[:, k].double() for k in range(3)])
    for i in range(0, 36, 5):
        c2w = path.c2w[i]
        local = (corners - c2w[:, 3]) @ c2w[:, :3]
        fx, fy, cx, cy = path.intrinsics[i]
        u = cx + fx * local[:, 0] / -local[:, 2]
        v = cy - fy * local[:, 1] / -local[:, 2]
        assert bool(((u >= 0) & (u <= 64) & (v >= 0) & (v <= 48) & (local[:, 2] < 0)).all())


def test_an_orbit_at_an_altitude_is_that_high_above_the_centre():
    path = orbit(AABB, 8, 32, 32, pitch_deg=45, altitude=2.0)
    assert torch.allclose(path.c2w[:, 2, 3], torch.full((8,), 2.0, dtype=torch.float64))
    assert fitting_distance(AABB, math.radians(45), 50, 32, 32) > 1.0


def test_a_flyover_follows_the_training_cameras_and_a_spiral_looks_at_the_box(tiny_scene):
    cams = tiny_scene.train.cameras
    path = flyover(cams, 30, 64, 48, smoothing=0.0)
    assert rotation_error(path.c2w).max() < 1e-9
    # unsmoothed, the path passes through the first and the last training camera
    assert torch.allclose(path.c2w[0, :, 3], cams.centers[0].double(), atol=1e-5)
    assert torch.allclose(path.c2w[-1, :, 3], cams.centers[-1].double(), atol=1e-5)
    nearest = torch.cdist(path.c2w[:, :, 3], cams.centers.double()).min(dim=1).values
    spacing = torch.cdist(cams.centers.double(), cams.centers.double())
    assert nearest.max() < spacing[spacing > 0].max()
    smooth = flyover(cams, 30, 64, 48, smoothing=0.2)
    assert rotation_error(smooth.c2w).max() < 1e-9
    sp = spiral(cams, tiny_scene.bounds.aabb, 20, 64, 48)
    assert rotation_error(sp.c2w).max() < 1e-9
    target = 0.5 * tiny_scene.bounds.aabb.double().sum(0)
    for i in (0, 7, 13):
        o, d = centre_ray(sp, i)
        assert ((o - target) - ((o - target) @ d) * d).norm() < 1e-3
    with pytest.raises(PathError, match="at least two"):
        flyover(cams.index([0]), 10, 32, 32)


def test_a_user_pose_goes_from_the_dataset_frame_to_the_world_and_back():
    angle = 0.3
    axes = torch.tensor(
        [
            [math.cos(angle), -math.sin(angle), 0],
            [math.sin(angle), math.cos(angle), 0],
            [0, 0, 1.0],
        ],
        dtype=torch.float64,
    )
    norm = Normalization(
        axes=axes,
        origin=torch.tensor([500.0, -20.0, 3.0], dtype=torch.float64),
        scale=80.0,
        units="metres",
    )
    pose = look_at(
        torch.tensor([480.0, 30.0, 60.0], dtype=torch.float64),
        torch.tensor([470.0, 0.0, 0.0], dtype=torch.float64),
    )
    world = source_to_world_pose(pose, norm)
    assert rotation_error(world[None]).max() < 1e-9
    assert torch.allclose(world[:, 3], norm.to_world(pose[None, :, 3])[0])
    assert torch.allclose(world_to_source_pose(world, norm), pose, atol=1e-9)
    path = user_path(
        [torch.cat([pose, torch.tensor([[0, 0, 0, 1.0]])]).tolist()],
        [[30, 30, 16, 12]],
        32,
        24,
        norm,
    )
    assert torch.allclose(path.c2w[0], world, atol=1e-9)


def test_what_is_not_a_camera_is_refused_naming_its_field():
    stretched = [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]
    with pytest.raises(PathError) as error:
        user_path(
            [
                look_at(
                    torch.ones(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)
                ).tolist(),
                stretched,
            ],
            [[1, 1, 1, 1]] * 2,
            8,
            8,
            None,
        )
    assert error.value.field == "path.cameras.1.c2w" and "not a rotation" in error.value.message
    with pytest.raises(ValidationError) as refused:
        RenderConfig.model_validate(
            {
                "path": {
                    "kind": "cameras",
                    "cameras": [
                        {"c2w": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]},
                        {"c2w": stretched},
                    ],
                }
            }
        )
    (e,) = refused.value.errors()
    assert e["loc"] == ("path", "cameras", "cameras", 1, "c2w") and "not a rotation" in e["msg"]
    # det -1: a reflection is not a camera either
    mirrored = [[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]
    with pytest.raises(ValidationError, match="not a rotation"):
        ViewRequest.model_validate({"camera": {"c2w": mirrored}})


@pytest.mark.parametrize(
    "body, field",
    [
        ({"path": {"kind": "helix"}}, ("path",)),
        ({"frames": 5000}, ("frames",)),
        ({"frames": 1000, "width": 640, "height": 480}, ("frames",)),
        ({"width": 321}, ("width",)),
        ({"width": 4000}, ("width",)),
        ({"fps": float("inf")}, ("fps",)),
        ({"appearance": "median"}, ("appearance",)),
        ({"path": {"kind": "orbit", "pitch_deg": 95}}, ("path", "orbit", "pitch_deg")),
        # altitude / sin(0)
        ({"path": {"kind": "orbit", "pitch_deg": 0, "altitude": 2.0}}, ("path", "orbit")),
    ],
)
def test_bad_render_settings_are_refused_naming_the_field(body, field):
    with pytest.raises(ValidationError) as refused:
        RenderConfig.model_validate(body)
    assert any(tuple(e["loc"][: len(field)]) == field for e in refused.value.errors()), (
        refused.value.errors()
    )


def test_a_user_path_counts_its_cameras_against_the_pixel_budget():
    camera = {"c2w": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}
    frames = MAX_VIDEO_PIXELS // (640 * 480) + 1
    with pytest.raises(ValidationError) as refused:
        RenderConfig.model_validate(
            {"width": 640, "height": 480, "path": {"kind": "cameras", "cameras": [camera] * frames}}
        )
    assert refused.value.errors()[0]["loc"] == ("path",)
    ok = RenderConfig.model_validate({"path": {"kind": "cameras", "cameras": [camera] * 3}})
    assert ok.frame_count == 3


def test_nerfstudio_camera_path_files_are_read(tmp_path):
    frame = {
        "camera_to_world": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 5, 0, 0, 0, 1],
        "fov": 40,
        "aspect": 1.33,
    }
    file = {
        "camera_type": "perspective",
        "render_width": 64,
        "render_height": 48,
        "camera_path": [frame] * 4,
        "fps": 24,
        "keyframes": [],
        "smoothness_value": 0.5,
    }
    cfg = RenderConfig.model_validate(
        {"path": {**json.loads(json.dumps(file)), "kind": "nerfstudio"}}
    )
    assert cfg.frame_count == 4 and cfg.path.camera_path[0].fov == 40
    with pytest.raises(ValidationError, match="not a rotation"):
        RenderConfig.model_validate(
            {
                "path": {
                    "kind": "nerfstudio",
                    "camera_path": [
                        {
                            **frame,
                            "camera_to_world": [1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 5, 0, 0, 0, 1],
                        }
                    ],
                }
            }
        )


def test_keyframes_interpolate_into_a_smooth_path():
    a = look_at(torch.tensor([2.0, 0, 1], dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    b = look_at(torch.tensor([0.0, 2, 1], dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    keys = user_path([a.tolist(), b.tolist()], [[40, 40, 16, 12], [60, 60, 16, 12]], 32, 24, None)
    path = interpolate(keys, 11)
    assert len(path) == 11 and rotation_error(path.c2w).max() < 1e-9
    assert torch.allclose(path.c2w[0], a) and torch.allclose(path.c2w[-1], b)
    assert torch.allclose(path.intrinsics[5], torch.tensor([50, 50, 16, 12], dtype=torch.float64))
    # halfway, the rotation is halfway: turned 45 degrees about z from the first, at the same
    # elevation
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    yaw = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=torch.float64)
    assert torch.allclose(path.c2w[5, :, :3], yaw @ a[:, :3], atol=1e-6)
    with pytest.raises(ValidationError, match="at least two"):
        RenderConfig.model_validate(
            {
                "path": {
                    "kind": "cameras",
                    "interpolate": True,
                    "cameras": [{"c2w": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}],
                }
            }
        )
    cfg = RenderConfig.model_validate(
        {
            "frames": 30,
            "path": {
                "kind": "cameras",
                "interpolate": True,
                "cameras": [{"c2w": a.tolist()}, {"c2w": b.tolist()}],
            },
        }
    )
    assert cfg.frame_count == 30

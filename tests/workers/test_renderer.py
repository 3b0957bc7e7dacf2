"""The one renderer (workers/renderer.py): chunking never changes what a method renders, a camera's
pixels come row by row, and depth becomes a picture by one rule (near bright, transparent black,
percentile range)."""

import torch

from model.methods import get_method
from model.profiles import get_profile
from model.scenes.bounds import ray_aabb
from model.scenes.cameras import make_cameras
from model.scenes.rays import RayBatch
from workers.renderer import Rendering, camera_rays, depth_grey, depth_range, render_rays

AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def rays(n: int, seed: int = 0) -> RayBatch:
    g = torch.Generator().manual_seed(seed)
    origins = torch.tensor([0.0, 0.0, 3.0]) + 0.3 * torch.randn(n, 3, generator=g)
    directions = torch.nn.functional.normalize(
        torch.tensor([0.0, 0.0, -1.0]) + 0.2 * torch.randn(n, 3, generator=g), dim=-1
    )
    near, far = ray_aabb(origins, directions, AABB)
    return RayBatch(
        origins,
        directions,
        near,
        far,
        torch.zeros(n, dtype=torch.long),
        torch.zeros(n, 3),
        torch.arange(n),
    )


def test_chunks_do_not_change_what_a_method_renders():
    torch.manual_seed(0)
    method = get_method("switch")(get_profile("smoke"))
    models = method.build(1, AABB)
    models.train()
    whole = render_rays(method, models, "main", rays(50), chunk=4096)
    pieces = render_rays(method, models, "main", rays(50), chunk=7)
    assert models.training  # the caller's mode is given back
    assert torch.allclose(whole.rgb, pieces.rgb, atol=1e-6) and torch.allclose(
        whole.depth, pieces.depth, atol=1e-5
    )
    assert torch.allclose(whole.opacity, pieces.opacity, atol=1e-6)
    v = get_profile("smoke").vanilla
    assert whole.samples_per_ray == pieces.samples_per_ray == v.coarse_samples + v.fine_samples
    assert whole.rgb.shape == (50, 3) and ((whole.rgb >= 0) & (whole.rgb <= 1)).all()


def test_a_camera_is_rendered_row_by_row():
    c2w = torch.tensor([[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3]]])
    cameras = make_cameras(
        torch.tensor([[4.0, 4.0, 2.0, 1.5]]), c2w, torch.tensor([4]), torch.tensor([3])
    )
    batch = camera_rays(cameras, 0, AABB, appearance=5)
    assert len(batch) == 12 and (batch.image_index == 5).all()
    # Pixel (u, v) sits at index v * width + u: along a row x grows, down the rows y falls (OpenGL
    # camera axes).
    assert (
        batch.directions[1, 0] > batch.directions[0, 0]
        and batch.directions[4, 1] < batch.directions[0, 1]
    )


def test_depth_becomes_grey_by_one_rule():
    distance = torch.linspace(1.0, 2.0, 100)
    opacity = torch.ones(100)
    opacity[:10] = 0.0  # transparent: no surface seen, black whatever its depth
    seen = Rendering(torch.zeros(100, 3), distance * opacity, opacity, 0.0)
    near, far = depth_range(seen)
    kept = distance[10:]
    assert (
        abs(near - float(torch.quantile(kept, 0.01))) < 1e-6
        and abs(far - float(torch.quantile(kept, 0.99))) < 1e-6
    )
    grey = depth_grey(seen.reshape(10, 10), near, far)
    assert grey.shape == (10, 10, 3) and grey.dtype == torch.uint8
    flat = grey[..., 0].reshape(-1)
    assert (flat[:10] == 0).all() and flat[10] == 255 and flat[-1] == 0  # near bright, far dark
    assert (flat[10:].int().diff() <= 0).all()
    assert depth_range(Rendering(torch.zeros(4, 3), torch.zeros(4), torch.zeros(4), 0.0)) == (
        0.0,
        1.0,
    )

"""Rendering whole frames from any camera with a finished run's own sampler: the frames of a video,
a viewer's preview, the depth an exported point cloud is made of. Each method renders as it does in
validation (LeCO through its occupancy, the grid through its cells, vanilla with its full sample budget), so
a method's sampling cost shows in its render time as it does in training."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from model.scenes.bounds import ray_aabb
from model.scenes.cameras import Cameras, pixel_rays
from model.scenes.rays import RayBatch
from workers.appearance import phase_embeddings
from workers.trained import Trained

CHUNK = 8192  # rays per forward pass (no gradient: memory is activations of one chunk)


@dataclass
class Frame:
    rgb: Tensor  # (H, W, 3) float in [0, 1]
    depth: Tensor  # (H, W) expected distance along the unit ray, world units (0 where nothing is hit)
    opacity: Tensor  # (H, W) the foreground's accumulated opacity
    samples_per_ray: float  # main-network samples the method spent per ray
    rays: RayBatch  # the frame's rays, row by row

    def surface_points(self, min_opacity: float) -> tuple[Tensor, Tensor]:
        """World points at the expected depth of the rays at least `min_opacity` opaque (depth over opacity:
        the distance given the ray hits), and the mask of those pixels (H, W)."""
        keep = (self.opacity >= min_opacity) & (self.opacity > 0)
        flat = keep.reshape(-1)
        depth = (self.depth / self.opacity.clamp(min=1e-6)).reshape(-1)[flat].double()
        return self.rays.origins[flat].double() + self.rays.directions[flat].double() * depth[:, None], keep


def appearance_row(trained: Trained, choice: str | int) -> int:
    """The appearance-embedding row a render uses: a training image's own (`choice`: its index in the training
    split), or 'mean', the mean of the training views' rows, appended once as a row of its own (the networks
    are a loaded copy; training never sees it)."""
    train = trained.scene.train.appearance
    if choice != "mean":
        if not 0 <= int(choice) < len(train):
            raise ValueError(f"appearance: training image {choice} does not exist (the run has {len(train)})")
        return int(train[int(choice)])
    if trained.mean_row is None:
        rows = train.to(trained.device)
        for embedding in phase_embeddings(trained.method, trained.models, "main"):
            weight = embedding.weight.detach()
            embedding.weight = nn.Parameter(torch.cat([weight, weight[rows].mean(dim=0, keepdim=True)]),
                                            requires_grad=False)
            embedding.num_embeddings = embedding.weight.shape[0]
        trained.mean_row = trained.scene.num_images
    return trained.mean_row


def frame_rays(cameras: Cameras, index: int, aabb: Tensor, appearance: int) -> RayBatch:
    """Every pixel of camera `index`, row by row."""
    width, height = int(cameras.width[index]), int(cameras.height[index])
    v, u = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    cam = torch.full((width * height,), index, dtype=torch.long)
    origins, directions = pixel_rays(cameras, cam, u.reshape(-1), v.reshape(-1))
    origins, directions = origins.float(), directions.float()
    near, far = ray_aabb(origins, directions, aabb)
    n = width * height
    return RayBatch(origins, directions, near, far, torch.full((n,), appearance, dtype=torch.long),
                    torch.zeros(n, 3), torch.arange(n))


@torch.no_grad()
def render_frame(trained: Trained, cameras: Cameras, index: int, appearance: int) -> Frame:
    rays = frame_rays(cameras, index, trained.scene.bounds.aabb.float(), appearance)
    rgb, depth, opacity, samples = [], [], [], 0
    trained.models.eval()
    for s in range(0, len(rays), CHUNK):
        chunk = RayBatch(*(getattr(rays, f)[s : s + CHUNK] for f in RayBatch.__dataclass_fields__))
        out = trained.method.render(trained.models, "main", chunk.to(trained.device))
        rgb.append(out.rgb.float().clamp(0, 1).cpu())
        depth.append(out.depth.float().cpu())
        opacity.append(out.opacity.float().cpu())
        samples += out.weights.numel()
    h, w = int(cameras.height[index]), int(cameras.width[index])
    return Frame(torch.cat(rgb).reshape(h, w, 3), torch.cat(depth).reshape(h, w), torch.cat(opacity).reshape(h, w),
                 samples / len(rays), rays)


def to_uint8(rgb: Tensor) -> Tensor:
    return (rgb * 255).round().clamp(0, 255).byte()


def depth_uint8(frame: Frame, near: float, far: float) -> Tensor:
    """Depth as grey on a fixed range (near bright), black where the foreground is transparent: a video's
    frames share the range, so brightness does not flicker."""
    scaled = 1.0 - ((frame.depth - near) / max(far - near, 1e-8)).clamp(0, 1)
    grey = (scaled * frame.opacity.clamp(0, 1) * 255).round().byte()
    return grey[..., None].expand(*grey.shape, 3).contiguous()

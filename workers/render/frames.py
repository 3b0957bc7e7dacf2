"""Rendering whole frames from any camera with a finished run's own sampler: the frames of a video,
a viewer's preview, the depth an exported point cloud is made of. Each method renders as it does in
validation (LeCO through its occupancy, the grid through its cells, vanilla with its full sample
budget), so a method's sampling cost shows in its render time as it does in training."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from model.scenes.cameras import Cameras
from model.scenes.rays import RayBatch
from workers.appearance import phase_embeddings
from workers.renderer import Rendering, camera_rays, render_rays
from workers.trained import Trained

CHUNK = 8192  # rays per forward pass of a frame


@dataclass
class Frame(Rendering):
    """A camera's rendering shaped (H, W), with its rays."""

    rays: RayBatch  # the frame's rays, row by row

    def surface_points(self, min_opacity: float) -> tuple[Tensor, Tensor]:
        """World points at the expected depth of the rays at least `min_opacity` opaque (depth over
        opacity: the distance given the ray hits), and the mask of those pixels (H, W)."""
        keep = (self.opacity >= min_opacity) & (self.opacity > 0)
        flat = keep.reshape(-1)
        depth = (self.depth / self.opacity.clamp(min=1e-6)).reshape(-1)[flat].double()
        return self.rays.origins[flat].double() + self.rays.directions[flat].double() * depth[
            :, None
        ], keep


def appearance_row(trained: Trained, choice: str | int) -> int:
    """The appearance-embedding row a render uses: a training image's own (`choice`: its index in
    the training split), or 'mean', the mean of the training views' rows, appended once as a row of
    its own (the networks are a loaded copy; training never sees it)."""
    train = trained.scene.train.appearance
    if choice != "mean":
        if not 0 <= int(choice) < len(train):
            raise ValueError(
                f"appearance: training image {choice} does not exist (the run has {len(train)})"
            )
        return int(train[int(choice)])
    if trained.mean_row is None:
        rows = train.to(trained.device)
        for embedding in phase_embeddings(trained.method, trained.models, "main"):
            weight = embedding.weight.detach()
            embedding.weight = nn.Parameter(
                torch.cat([weight, weight[rows].mean(dim=0, keepdim=True)]), requires_grad=False
            )
            embedding.num_embeddings = embedding.weight.shape[0]
        trained.mean_row = trained.scene.num_images
    return trained.mean_row


def render_frame(trained: Trained, cameras: Cameras, index: int, appearance: int) -> Frame:
    """Every pixel of camera `index` through the finished run's networks (workers/renderer.py)."""
    rays = camera_rays(cameras, index, trained.scene.bounds.aabb.float(), appearance)
    out = render_rays(trained.method, trained.models, "main", rays, trained.device, CHUNK)
    h, w = int(cameras.height[index]), int(cameras.width[index])
    shaped = out.reshape(h, w)
    return Frame(shaped.rgb, shaped.depth, shaped.opacity, shaped.samples_per_ray, rays)

"""Pinhole cameras (optionally OpenCV-distorted) in the project's one world convention.

World frame: right-handed, z up. Camera-to-world matrices use the OpenGL camera convention: the
columns of the 3x3 block are the camera's right, up and back axes (the camera looks along -back),
the last column is its centre. Pixel (u, v) (u column, v row) has its centre at (u + 0.5, v + 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor


@dataclass(frozen=True)
class Cameras:
    """N cameras. `distortion` holds OpenCV (k1, k2, p1, p2) per camera; zeros mean a pinhole."""

    intrinsics: Tensor  # (N, 4) float32: fx, fy, cx, cy in pixels
    c2w: Tensor  # (N, 3, 4) float32, OpenGL camera axes, world z up
    width: Tensor  # (N,) int64
    height: Tensor  # (N,) int64
    distortion: Tensor  # (N, 4) float32

    def __len__(self) -> int:
        return self.c2w.shape[0]

    @property
    def centers(self) -> Tensor:
        return self.c2w[:, :, 3]

    @property
    def forward(self) -> Tensor:
        """Unit viewing directions (-back)."""
        return -self.c2w[:, :, 2]

    def to(self, device: torch.device | str) -> Cameras:
        return Cameras(*(getattr(self, f).to(device) for f in self.__dataclass_fields__))

    def index(self, idx: Tensor | slice | list[int]) -> Cameras:
        return Cameras(
            self.intrinsics[idx],
            self.c2w[idx],
            self.width[idx],
            self.height[idx],
            self.distortion[idx],
        )

    def scaled(self, sx: Tensor, sy: Tensor) -> Cameras:
        """Cameras for images resized by per-camera factors (new size / old size)."""
        fx, fy, cx, cy = self.intrinsics.unbind(-1)
        intrinsics = torch.stack([fx * sx, fy * sy, cx * sx, cy * sy], dim=-1)
        width = torch.round(self.width * sx).long()
        height = torch.round(self.height * sy).long()
        return replace(self, intrinsics=intrinsics, width=width, height=height)

    def half_fov(self) -> Tensor:
        """Half of the smaller field of view per camera, in radians."""
        fx, fy = self.intrinsics[:, 0], self.intrinsics[:, 1]
        return torch.minimum(torch.atan(0.5 * self.width / fx), torch.atan(0.5 * self.height / fy))


def make_cameras(
    intrinsics: Tensor, c2w: Tensor, width: Tensor, height: Tensor, distortion: Tensor | None = None
) -> Cameras:
    """Poses stay float64 when given so (a reader's metres at city scale, before normalisation); a
    normalised Scene holds float32 poses."""
    n = c2w.shape[0]
    if distortion is None:
        distortion = torch.zeros(n, 4)
    return Cameras(
        intrinsics=intrinsics.float().reshape(n, 4),
        c2w=(c2w if c2w.dtype == torch.float64 else c2w.float()).reshape(n, 3, 4),
        width=width.long().reshape(n),
        height=height.long().reshape(n),
        distortion=distortion.float().reshape(n, 4),
    )


def undistort_opencv(
    xd: Tensor, yd: Tensor, k: Tensor, iterations: int = 10
) -> tuple[Tensor, Tensor]:
    """Invert the OpenCV (k1, k2, p1, p2) model on normalised image coordinates by Newton's
    method."""
    k1, k2, p1, p2 = k.unbind(-1)
    x, y = xd.clone(), yd.clone()
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * k2)
        fx_res = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd
        fy_res = y * radial + 2 * p2 * x * y + p1 * (r2 + 2 * y * y) - yd
        d_radial = k1 + 2 * r2 * k2  # d(radial)/d(r2)
        dfx_dx = radial + 2 * x * x * d_radial + 2 * p1 * y + 6 * p2 * x
        dfx_dy = 2 * x * y * d_radial + 2 * p1 * x + 2 * p2 * y
        dfy_dx = 2 * x * y * d_radial + 2 * p2 * y + 2 * p1 * x
        dfy_dy = radial + 2 * y * y * d_radial + 2 * p2 * x + 6 * p1 * y
        det = dfx_dx * dfy_dy - dfx_dy * dfy_dx
        det = torch.where(det.abs() < 1e-12, torch.full_like(det, 1e-12), det)
        x = x - (fx_res * dfy_dy - fy_res * dfx_dy) / det
        y = y - (fy_res * dfx_dx - fx_res * dfy_dx) / det
    return x, y


def pixel_rays(
    cameras: Cameras, cam_index: Tensor, u: Tensor, v: Tensor, distorted: bool | None = None
) -> tuple[Tensor, Tensor]:
    """World-space origins and unit directions of the rays through pixel centres (u, v) of
    cameras[cam_index].

    u, v may be fractional (sub-pixel positions); a pixel's centre is at integer u, v here + 0.5.
    `distorted`: whether any of these cameras has distortion, when the caller knows it (a training
    batch's table decides once, so drawing a batch on a GPU never waits to read it); None: read.
    """
    intr = cameras.intrinsics[cam_index]
    fx, fy, cx, cy = intr.unbind(-1)
    x = (u.float() + 0.5 - cx) / fx
    y = (v.float() + 0.5 - cy) / fy  # OpenCV image coordinates: y points down
    k = cameras.distortion[cam_index]
    if distorted if distorted is not None else bool(k.any()):
        x, y = undistort_opencv(x, y, k)  # zeros for an undistorted camera change nothing
    # OpenGL camera: x right, y up, looking along -z.
    d_cam = torch.stack([x, -y, -torch.ones_like(x)], dim=-1)
    c2w = cameras.c2w[cam_index]
    d_world = torch.einsum("nij,nj->ni", c2w[:, :, :3], d_cam.to(c2w.dtype))
    d_world = d_world / d_world.norm(dim=-1, keepdim=True)
    return c2w[:, :, 3].expand_as(d_world).contiguous(), d_world


def rotation_error(c2w: Tensor) -> Tensor:
    """Per-camera max |R^T R - I| and |det R - 1|: zero for a rigid (orthonormal, right-handed)
    pose."""
    r = c2w[:, :, :3].double()
    eye = torch.eye(3, dtype=r.dtype)
    ortho = (r.transpose(1, 2) @ r - eye).abs().amax(dim=(1, 2))
    det = (torch.linalg.det(r) - 1).abs()
    return torch.maximum(ortho, det)

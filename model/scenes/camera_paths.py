"""Camera paths for videos and views: generated ones around a scene's foreground box or along its
training cameras, and user paths given as camera-to-world matrices. Everything here is in the
normalised world frame (model/scenes/scene.py: z up, the foreground box centred at the origin, its
longest side spanning [-1, 1]) with OpenGL camera axes; `user_path` takes cameras in the dataset's
own frame and converts them.

- orbit: around the box centre at a pitch below the horizon, at an altitude (or, by default, far
  enough that the box's bounding sphere fills the view);
- flyover: along the training cameras in capture order, smoothed (a Gaussian over the sequence) and
  resampled evenly by arc length, each looking the way the smoothed cameras look;
- spiral: LLFF's render path, a spiral around the mean training camera looking at the box centre
  (the one path a forward-facing capture like fern can show without its unseen back).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from model.errors import InvalidInput
from model.scenes.cameras import Cameras, make_cameras
from model.scenes.rotation import rotation_problem
from model.scenes.scene import Normalization, Scene

UP = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


class PathError(InvalidInput):
    """A camera path that cannot be rendered; `field` names what is wrong (e.g.
    `path.cameras.3.c2w`)."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field, self.message = field, message


@dataclass(frozen=True)
class CameraPath:
    c2w: Tensor  # (N, 3, 4) float64, world frame, OpenGL axes
    intrinsics: Tensor  # (N, 4) float64: fx, fy, cx, cy at width x height
    width: int
    height: int

    def __len__(self) -> int:
        return self.c2w.shape[0]

    def cameras(self) -> Cameras:
        n = len(self)
        return make_cameras(
            self.intrinsics.float(),
            self.c2w.float(),
            torch.full((n,), self.width),
            torch.full((n,), self.height),
        )

    def frame(self, i: int) -> Cameras:
        return self.cameras().index([i])


def intrinsics_for_fov(fov_deg: float, width: int, height: int) -> Tensor:
    """fx = fy from a vertical field of view (nerfstudio's convention), principal point at the
    centre."""
    f = 0.5 * height / math.tan(math.radians(fov_deg) / 2)
    return torch.tensor([f, f, width / 2, height / 2], dtype=torch.float64)


def look_at(position: Tensor, target: Tensor, up: Tensor = UP) -> Tensor:
    """(3, 4) OpenGL camera-to-world at `position` looking at `target`; columns right, up, back,
    centre."""
    back = position - target
    back = back / back.norm()
    right = torch.linalg.cross(up.to(back), back)
    if float(right.norm()) < 1e-9:  # looking straight up or down: any horizontal right axis will do
        right = torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0], dtype=back.dtype), back)
    right = right / right.norm()
    return torch.stack([right, torch.linalg.cross(back, right), back, position], dim=1)


def look_along(position: Tensor, forward: Tensor) -> Tensor:
    return look_at(position, position + forward)


def box_centre_and_radius(aabb: Tensor) -> tuple[Tensor, float]:
    aabb = aabb.double()
    return 0.5 * (aabb[0] + aabb[1]), float(0.5 * (aabb[1] - aabb[0]).norm())


def fitting_distance(
    aabb: Tensor, pitch: float, fov_deg: float, width: int, height: int, margin: float = 1.05
) -> float:
    """The distance from the box centre at which, seen from any heading at this pitch, all eight
    corners of the box are in view: a corner at (right r, up u, forward f) from the centre is in
    view from distance d when
    |r| <= tan(half horizontal fov) (d + f) and |u| <= tan(half vertical fov) (d + f)."""
    centre = box_centre_and_radius(aabb)[0]
    lo, hi = aabb.double()
    corners = torch.stack(
        torch.meshgrid(*[torch.stack([lo[k], hi[k]]) for k in range(3)], indexing="ij"), -1
    )
    corners = corners.reshape(-1, 3) - centre
    tan_v = math.tan(math.radians(fov_deg) / 2)
    tan_h = tan_v * width / height
    distance = 0.0
    for theta in torch.linspace(0, 2 * math.pi, 24)[:-1].tolist():
        back = torch.tensor(
            [math.cos(pitch) * math.cos(theta), math.cos(pitch) * math.sin(theta), math.sin(pitch)],
            dtype=torch.float64,
        )
        axes = look_at(back, torch.zeros(3, dtype=torch.float64))[:, :3]
        r, u, b = (corners @ axes).unbind(-1)
        need = torch.maximum(r.abs() / tan_h, u.abs() / tan_v) + b  # forward = -back
        distance = max(distance, float(need.max()))
    return distance * margin


def orbit(
    aabb: Tensor,
    frames: int,
    width: int,
    height: int,
    *,
    fov_deg: float = 50.0,
    pitch_deg: float = 30.0,
    altitude: float | None = None,
    turns: float = 1.0,
) -> CameraPath:
    """`altitude`: world units above the box centre (None: the whole box in view from every
    heading)."""
    centre, _ = box_centre_and_radius(aabb)
    pitch = math.radians(pitch_deg)
    distance = (
        altitude / math.sin(pitch)
        if altitude is not None
        else fitting_distance(aabb, pitch, fov_deg, width, height)
    )
    poses = []
    for i in range(frames):
        theta = 2 * math.pi * turns * i / frames
        offset = torch.tensor(
            [math.cos(pitch) * math.cos(theta), math.cos(pitch) * math.sin(theta), math.sin(pitch)],
            dtype=torch.float64,
        )
        poses.append(look_at(centre + distance * offset, centre))
    return CameraPath(
        torch.stack(poses),
        intrinsics_for_fov(fov_deg, width, height).expand(frames, 4).clone(),
        width,
        height,
    )


def training_order(scene: Scene) -> Cameras:
    """The training cameras in capture order (by image name)."""
    order = sorted(range(len(scene.train)), key=lambda i: scene.train.names[i])
    return scene.train.cameras.index(order)


def training_fov_deg(cameras: Cameras) -> float:
    """The median vertical field of view of a set of cameras."""
    fy, h = cameras.intrinsics[:, 1].double(), cameras.height.double()
    return float(torch.rad2deg(2 * torch.atan(0.5 * h / fy)).median())


def gaussian_smooth(values: Tensor, sigma: float) -> Tensor:
    """Along the first axis, with the kernel renormalised at the ends (no pull towards zero)."""
    if sigma <= 0 or len(values) < 3:
        return values
    index = torch.arange(len(values), dtype=torch.float64)
    kernel = torch.exp(-0.5 * ((index[:, None] - index[None, :]) / sigma) ** 2)
    return (kernel @ values) / kernel.sum(dim=1, keepdim=True)


def resample_by_arc_length(points: Tensor, frames: int) -> tuple[Tensor, Tensor]:
    """Indices (fractional) into `points` at `frames` evenly spaced arc lengths: (lower index,
    weight)."""
    steps = (points[1:] - points[:-1]).norm(dim=-1)
    arc = torch.cat([torch.zeros(1, dtype=points.dtype), steps.cumsum(0)])
    if float(arc[-1]) <= 0:  # every camera at one place: step through them evenly instead
        arc = torch.arange(len(points), dtype=points.dtype)
    wanted = torch.linspace(0, float(arc[-1]), frames, dtype=points.dtype)
    lower = (torch.searchsorted(arc, wanted, right=True) - 1).clamp(0, len(points) - 2)
    span = (arc[lower + 1] - arc[lower]).clamp(min=1e-12)
    return lower, ((wanted - arc[lower]) / span).clamp(0, 1)


def flyover(
    cameras: Cameras,
    frames: int,
    width: int,
    height: int,
    *,
    fov_deg: float | None = None,
    smoothing: float = 0.05,
) -> CameraPath:
    """Along `cameras` (in capture order); `smoothing`: the Gaussian's sigma as a fraction of the
    cameras."""
    if len(cameras) < 2:
        raise PathError("path.kind", "a flyover needs at least two training cameras")
    sigma = smoothing * len(cameras)
    centres = gaussian_smooth(cameras.centers.double(), sigma)
    forwards = gaussian_smooth(cameras.forward.double(), sigma)
    lower, w = resample_by_arc_length(centres, frames)
    position = centres[lower] * (1 - w[:, None]) + centres[lower + 1] * w[:, None]
    forward = forwards[lower] * (1 - w[:, None]) + forwards[lower + 1] * w[:, None]
    poses = torch.stack([look_along(p, f / f.norm()) for p, f in zip(position, forward)])
    fov = fov_deg if fov_deg is not None else training_fov_deg(cameras)
    return CameraPath(
        poses, intrinsics_for_fov(fov, width, height).expand(frames, 4).clone(), width, height
    )


def spiral(
    cameras: Cameras,
    aabb: Tensor,
    frames: int,
    width: int,
    height: int,
    *,
    fov_deg: float | None = None,
    turns: float = 2.0,
    spread: float = 1.0,
) -> CameraPath:
    """LLFF's spiral: around the mean training camera, in its own image plane (radii: the 90th
    percentile of the cameras' offsets from it along its axes, times `spread`), with a slower bob
    along its viewing axis; every frame looks at the foreground box's centre."""
    centres = cameras.centers.double()
    mean = centres.mean(dim=0)
    forward = cameras.forward.double().mean(dim=0)
    frame = look_along(mean, forward / forward.norm())[:, :3]  # right, up, back of the mean camera
    offsets = ((centres - mean) @ frame).abs()
    radii = torch.quantile(offsets, 0.9, dim=0).clamp(min=1e-3) * spread
    target, _ = box_centre_and_radius(aabb)
    poses = []
    for i in range(frames):
        theta = 2 * math.pi * turns * i / frames
        local = torch.tensor(
            [math.cos(theta), -math.sin(theta), -math.sin(theta / turns) * 0.5], dtype=torch.float64
        )
        poses.append(look_at(mean + frame @ (local * radii), target))
    fov = fov_deg if fov_deg is not None else training_fov_deg(cameras)
    return CameraPath(
        torch.stack(poses),
        intrinsics_for_fov(fov, width, height).expand(frames, 4).clone(),
        width,
        height,
    )


def slerp_rotations(r0: Tensor, r1: Tensor, t: float) -> Tensor:
    """The rotation a fraction t of the way from r0 to r1 along the shortest arc (axis-angle of r0^T
    r1)."""
    delta = r0.T @ r1
    angle = math.acos(max(-1.0, min(1.0, (float(torch.trace(delta)) - 1) / 2)))
    if angle < 1e-9:
        return r0.clone()
    axis = torch.stack(
        [delta[2, 1] - delta[1, 2], delta[0, 2] - delta[2, 0], delta[1, 0] - delta[0, 1]]
    )
    # half a turn: the axis is the eigenvector of delta with eigenvalue 1
    if float(axis.norm()) < 1e-9:
        values, vectors = torch.linalg.eigh(0.5 * (delta + delta.T))
        axis = vectors[:, int(values.argmax())]
    axis = axis / axis.norm()
    k = torch.tensor(
        [[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=r0.dtype
    )
    a = angle * t
    return r0 @ (torch.eye(3, dtype=r0.dtype) + math.sin(a) * k + (1 - math.cos(a)) * k @ k)


def interpolate(path: CameraPath, frames: int) -> CameraPath:
    """`frames` cameras through a path's cameras taken as keyframes: centres evenly spaced along the
    polyline's arc length, rotations and intrinsics interpolated between the two keyframes around
    each (the viewer's saved cameras become a smooth fly-through)."""
    if len(path) < 2:
        raise PathError("path.cameras", "interpolating a path needs at least two cameras")
    lower, w = resample_by_arc_length(path.c2w[:, :, 3], frames)
    poses, intrinsics = [], []
    for i, t in zip(lower.tolist(), w.tolist()):
        a, b = path.c2w[i], path.c2w[i + 1]
        rotation = slerp_rotations(a[:, :3], b[:, :3], t)
        poses.append(torch.cat([rotation, (a[:, 3] * (1 - t) + b[:, 3] * t)[:, None]], dim=1))
        intrinsics.append(path.intrinsics[i] * (1 - t) + path.intrinsics[i + 1] * t)
    return CameraPath(torch.stack(poses), torch.stack(intrinsics), path.width, path.height)


def check_rotation(c2w: Tensor, field: str) -> None:
    problem = rotation_problem(c2w.double().reshape(3, 4).tolist())
    if problem is not None:
        raise PathError(field, problem)


def source_to_world_pose(c2w: Tensor, normalization: Normalization) -> Tensor:
    """A (3, 4) camera-to-world in the dataset's own frame -> the world frame (rotation by the
    normalisation's axes, centre through the same map as every point)."""
    c2w = c2w.double()
    rotation = normalization.axes.double() @ c2w[:, :3]
    centre = normalization.to_world(c2w[None, :, 3])[0]
    return torch.cat([rotation, centre[:, None]], dim=1)


def world_to_source_pose(c2w: Tensor, normalization: Normalization) -> Tensor:
    c2w = c2w.double()
    rotation = normalization.axes.double().T @ c2w[:, :3]
    centre = normalization.to_source(c2w[None, :, 3])[0]
    return torch.cat([rotation, centre[:, None]], dim=1)


def user_path(
    c2w: list,
    intrinsics: list,
    width: int,
    height: int,
    normalization: Normalization | None,
    field: str = "path.cameras",
) -> CameraPath:
    """Cameras a user gave: 3x4 or 4x4 camera-to-world matrices (the dataset's own frame when
    `normalization` is given, else already the world frame) and fx, fy, cx, cy at width x height.
    Each pose must be a rotation and a centre: the field of the first that is not is named."""
    poses = []
    for i, matrix in enumerate(c2w):
        m = torch.tensor(matrix, dtype=torch.float64)
        if m.shape == (4, 4):
            m = m[:3]
        if m.shape != (3, 4):
            raise PathError(
                f"{field}.{i}.c2w", f"must be a 3x4 or 4x4 matrix, got shape {tuple(m.shape)}"
            )
        check_rotation(m, f"{field}.{i}.c2w")
        poses.append(source_to_world_pose(m, normalization) if normalization is not None else m)
    return CameraPath(
        torch.stack(poses),
        torch.tensor(intrinsics, dtype=torch.float64).reshape(-1, 4),
        width,
        height,
    )

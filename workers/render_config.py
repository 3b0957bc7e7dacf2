"""What a render, a view or an export of a finished run asks for: one pydantic schema each, from the
API request down to the worker that renders (like workers/config.py for training). Bounded on both sides and
finite; a field that is wrong is named by its path (`path.cameras.3.c2w`, `frames`, `width`)."""

from __future__ import annotations

from typing import Annotated, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from model.rotation import rotation_problem

RENDER_PHASE = "render"  # a render job's one phase: a step a frame
EXPORT_PHASE = "export"  # an export job's: a step a view of a point cloud (one otherwise)
MAX_FRAMES = 1200
MAX_SIDE = 1920
MAX_FRAME_PIXELS = 1920 * 1080
MAX_VIDEO_PIXELS = 60_000_000  # frames x pixels of one render job: 780 frames of 320x240, 195 of 640x480
MAX_VIEW_SIDE = 640  # a view is a preview (POST /v1/jobs/{id}/view)
MAX_VIEW_PIXELS = 640 * 480
MIN_ALTITUDE_PITCH_DEG = 1.0  # an orbit at an altitude is at most 57x that altitude from the box

Finite = Annotated[float, Field(ge=-1e9, le=1e9)]
STRICT = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class Camera(BaseModel):
    """One camera: a camera-to-world matrix (OpenGL axes: right, up, back, centre; 3x4 or 4x4 row by row) and
    either pinhole intrinsics fx, fy, cx, cy at the path's size or a vertical field of view."""

    model_config = STRICT

    c2w: list[Annotated[list[Finite], Field(min_length=4, max_length=4)]] = Field(min_length=3, max_length=4)
    intrinsics: Annotated[list[Annotated[float, Field(gt=0, le=1e6)]], Field(min_length=4, max_length=4)] | None = None
    fov_deg: float = Field(50.0, gt=1, lt=170, description="vertical field of view, used without intrinsics")

    @field_validator("c2w")
    @classmethod
    def a_rotation_and_a_centre(cls, c2w: list[list[float]]) -> list[list[float]]:
        if len(c2w) == 4 and [float(v) for v in c2w[3]] != [0.0, 0.0, 0.0, 1.0]:
            raise ValueError("the last row of a 4x4 camera-to-world must be 0, 0, 0, 1")
        problem = rotation_problem(c2w)
        if problem is not None:
            raise ValueError(problem)
        return c2w


class OrbitPath(BaseModel):
    model_config = STRICT
    kind: Literal["orbit"] = "orbit"
    pitch_deg: float = Field(30.0, ge=0, le=89, description="below the horizon")
    altitude: float | None = Field(None, gt=0, le=1e7, description="above the foreground box's centre, in the "
                                   "dataset's units (metres where it has them); default: the box fills the view")
    turns: float = Field(1.0, gt=0, le=10)
    fov_deg: float = Field(50.0, gt=1, lt=170, description="vertical field of view")

    @model_validator(mode="after")
    def altitude_needs_a_pitch(self) -> "OrbitPath":
        # The orbit's distance is altitude / sin(pitch): at a level pitch no distance reaches that altitude.
        if self.altitude is not None and self.pitch_deg < MIN_ALTITUDE_PITCH_DEG:
            raise ValueError(f"an orbit at an altitude needs pitch_deg >= {MIN_ALTITUDE_PITCH_DEG:g} (the camera looks "
                             f"down at the box from altitude / sin(pitch)); got pitch_deg={self.pitch_deg:g} with "
                             f"altitude={self.altitude:g}: raise the pitch or leave the altitude out")
        return self


class FlyoverPath(BaseModel):
    model_config = STRICT
    kind: Literal["flyover"] = "flyover"
    smoothing: float = Field(0.05, ge=0, le=1, description="Gaussian sigma as a fraction of the training cameras")
    fov_deg: float | None = Field(None, gt=1, lt=170, description="default: the training cameras' median")


class SpiralPath(BaseModel):
    model_config = STRICT
    kind: Literal["spiral"] = "spiral"
    turns: float = Field(2.0, gt=0, le=10)
    spread: float = Field(1.0, gt=0, le=10, description="radius against the training cameras' spread")
    fov_deg: float | None = Field(None, gt=1, lt=170, description="default: the training cameras' median")


class CamerasPath(BaseModel):
    """A user's path: one camera per frame (or keyframes to interpolate), in the dataset's own frame (`source`)
    or the normalised world the API's cameras route and the dashboard's viewer use (`world`)."""

    model_config = STRICT
    kind: Literal["cameras"] = "cameras"
    frame: Literal["source", "world"] = "source"
    width: int | None = Field(None, ge=1, le=8192, description="the size the intrinsics are given at (default: "
                              "the render's)")
    height: int | None = Field(None, ge=1, le=8192)
    interpolate: bool = Field(False, description="the cameras are keyframes: render `frames` frames through them "
                              "(evenly along the path, rotations interpolated); else one frame per camera")
    cameras: list[Camera] = Field(min_length=1, max_length=MAX_FRAMES)

    @field_validator("cameras")
    @classmethod
    def keyframes(cls, cameras: list[Camera], info: ValidationInfo) -> list[Camera]:
        if info.data.get("interpolate") and len(cameras) < 2:
            raise ValueError("interpolating a path needs at least two cameras")
        return cameras


class NerfstudioFrame(BaseModel):
    model_config = ConfigDict(frozen=True, extra="ignore", allow_inf_nan=False)
    camera_to_world: list[Finite] = Field(min_length=16, max_length=16, description="4x4, row by row")
    fov: float = Field(gt=1, lt=170, description="vertical, degrees")

    @field_validator("camera_to_world")
    @classmethod
    def a_rotation_and_a_centre(cls, values: list[float]) -> list[float]:
        Camera.a_rotation_and_a_centre([values[i:i + 4] for i in range(0, 16, 4)])
        return values


class NerfstudioPath(BaseModel):
    """nerfstudio's camera_path.json (perspective cameras), read in the dataset's own frame."""

    model_config = ConfigDict(frozen=True, extra="ignore", allow_inf_nan=False)
    kind: Literal["nerfstudio"] = "nerfstudio"
    camera_type: Literal["perspective"] = "perspective"
    render_width: int | None = Field(None, ge=1, le=8192)
    render_height: int | None = Field(None, ge=1, le=8192)
    camera_path: list[NerfstudioFrame] = Field(min_length=1, max_length=MAX_FRAMES)


PathSpec = Annotated[Union[OrbitPath, FlyoverPath, SpiralPath, CamerasPath, NerfstudioPath],
                     Field(discriminator="kind")]
GENERATED = ("orbit", "flyover", "spiral")


def even_side(value: int) -> int:
    if value % 2:
        raise ValueError(f"must be even (H.264 in yuv420p halves both sides for colour), got {value}")
    return value


class RenderConfig(BaseModel):
    """A video of a finished run along a camera path. Fields are checked in order, so `frames` and `path`
    are refused with the size they would render at."""

    model_config = STRICT

    width: int = Field(320, ge=16, le=MAX_SIDE)
    height: int = Field(240, ge=16, le=MAX_SIDE)
    frames: int = Field(120, ge=2, le=MAX_FRAMES, description="of a generated path; a user path has one per camera")
    fps: float = Field(24.0, ge=1, le=60)
    appearance: Literal["mean"] | Annotated[int, Field(ge=0, le=2**31 - 1)] = Field(
        "mean", description="'mean' of the training views' appearance embeddings, or a training image's index")
    depth_video: bool = False
    path: PathSpec = Field(default_factory=OrbitPath)

    @field_validator("width", "height")
    @classmethod
    def even(cls, side: int) -> int:
        return even_side(side)

    @field_validator("frames")
    @classmethod
    def frames_within_budget(cls, frames: int, info: ValidationInfo) -> int:
        check_pixels(frames, info.data)
        return frames

    @field_validator("path")
    @classmethod
    def path_within_budget(cls, path, info: ValidationInfo):
        count = path_frames(path)
        if count is not None:
            check_pixels(count, info.data)
        return path

    @property
    def frame_count(self) -> int:
        count = path_frames(self.path)
        return self.frames if count is None else count


def path_frames(path) -> int | None:
    """A user path's frame count (one per camera), None for a generated path (`frames` sets it)."""
    if isinstance(path, CamerasPath):
        return None if path.interpolate else len(path.cameras)
    if isinstance(path, NerfstudioPath):
        return len(path.camera_path)
    return None


def check_pixels(frames: int, data: dict) -> None:
    width, height = data.get("width"), data.get("height")
    if width is None or height is None:
        return  # the size itself was refused: that error names it
    if width * height > MAX_FRAME_PIXELS:
        raise ValueError(f"{width}x{height} is {width * height:,} pixels a frame, more than {MAX_FRAME_PIXELS:,}")
    if frames * width * height > MAX_VIDEO_PIXELS:
        raise ValueError(f"{frames} frames of {width}x{height} are {frames * width * height:,} pixels, more than "
                         f"{MAX_VIDEO_PIXELS:,} a render job renders")


class ViewRequest(BaseModel):
    """One camera rendered to a PNG preview (the dashboard's viewer)."""

    model_config = STRICT

    camera: Camera
    frame: Literal["world", "source"] = "world"
    width: int = Field(160, ge=8, le=MAX_VIEW_SIDE)
    height: int = Field(120, ge=8, le=MAX_VIEW_SIDE)
    appearance: Literal["mean"] | Annotated[int, Field(ge=0, le=2**31 - 1)] = "mean"
    depth: bool = Field(False, description="a depth image instead of colour")

    @field_validator("height")
    @classmethod
    def preview_sized(cls, height: int, info: ValidationInfo) -> int:
        width = info.data.get("width")
        if width is not None and width * height > MAX_VIEW_PIXELS:
            raise ValueError(f"{width}x{height} is more than a {MAX_VIEW_PIXELS:,}-pixel preview")
        return height


class ExportConfig(BaseModel):
    """Geometry of a finished run in the dataset's own frame and units."""

    model_config = STRICT

    what: Literal["pointcloud", "cameras", "occupancy"]
    # pointcloud: expected-depth points of training and validation pixels whose rays are nearly opaque
    stride: int = Field(1, ge=1, le=64, description="every stride-th pixel along rows and columns")
    min_opacity: float = Field(0.9, ge=0, le=1, description="a ray's foreground opacity a point needs")
    max_points: int = Field(1_000_000, ge=1, le=20_000_000, description="seeded subsample beyond this")
    # occupancy: the cells of a regular grid over the foreground box that the method's occupancy keeps
    resolution: int = Field(128, ge=8, le=512)

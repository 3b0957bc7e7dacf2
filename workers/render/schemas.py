"""What a render, a view or an export of a finished run asks for: one pydantic schema each, from the
API request down to the worker that renders (like workers/config.py for training). Bounded on both
sides and finite; a field that is wrong is named by its path (`path.cameras.3.c2w`, `frames`,
`width`)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, Field, StrictInt, ValidationInfo, field_validator

from workers.render.camera_paths.base import MAX_FRAMES, STRICT, Camera, PathKind
from workers.render.camera_paths.orbit import OrbitPath
from workers.render.camera_paths.registry import on_change, path_type

RENDER_PHASE = "render"  # a render job's one phase: a step a frame
EXPORT_PHASE = "export"  # an export job's: a step a view of a point cloud (one otherwise)
MAX_SIDE = 1920
MAX_FRAME_PIXELS = 1920 * 1080
# frames x pixels of one render job: 780 frames of 320x240, 195 of 640x480
MAX_VIDEO_PIXELS = 60_000_000
MAX_VIEW_SIDE = 640  # a view is a preview (POST /v1/jobs/{id}/view)
MAX_VIEW_PIXELS = 640 * 480


def even_side(value: int) -> int:
    if value % 2:
        raise ValueError(
            f"must be even (H.264 in yuv420p halves both sides for colour), got {value}"
        )
    return value


class RenderConfig(BaseModel):
    """A video of a finished run along a camera path. Fields are checked in order, so `frames` and
    `path` are refused with the size they would render at."""

    model_config = STRICT

    width: StrictInt = Field(320, ge=16, le=MAX_SIDE, description="frame width in pixels (even)")
    height: StrictInt = Field(240, ge=16, le=MAX_SIDE, description="frame height in pixels (even)")
    frames: StrictInt = Field(
        120, ge=2, le=MAX_FRAMES, description="of a generated path; a user path has one per camera"
    )
    fps: float = Field(24.0, ge=1, le=60, description="frames per second of the video")
    appearance: Literal["mean"] | Annotated[StrictInt, Field(ge=0, le=2**31 - 1)] = Field(
        "mean",
        description="'mean' of the training views' appearance embeddings, or a training image's "
        "index",
    )
    depth_video: bool = Field(False, description="also a depth video, near light and far dark")
    path: path_type() = Field(  # type: ignore[valid-type]  # the registry's kinds
        default_factory=OrbitPath, description="the camera path, one of GET /v1/camera-paths"
    )

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
    def path_within_budget(cls, path: PathKind, info: ValidationInfo) -> PathKind:
        count = path.frame_count()
        if count is not None:
            check_pixels(count, info.data)
        return path

    @property
    def frame_count(self) -> int:
        count = self.path.frame_count()
        return self.frames if count is None else count


def follow_the_registry() -> None:
    """A kind registered after this module was imported (a plug-in, a test's toy) is a `path`
    too."""
    RenderConfig.model_fields["path"].annotation = path_type()
    RenderConfig.__annotations__["path"] = path_type()
    RenderConfig.model_rebuild(force=True)


on_change(follow_the_registry)


def check_pixels(frames: int, data: dict) -> None:
    width, height = data.get("width"), data.get("height")
    if width is None or height is None:
        return  # the size itself was refused: that error names it
    if width * height > MAX_FRAME_PIXELS:
        raise ValueError(
            f"{width}x{height} is {width * height:,} pixels a frame, more than {MAX_FRAME_PIXELS:,}"
        )
    if frames * width * height > MAX_VIDEO_PIXELS:
        raise ValueError(
            f"{frames} frames of {width}x{height} are {frames * width * height:,} pixels, more "
            f"than {MAX_VIDEO_PIXELS:,} a render job renders"
        )


class ViewRequest(BaseModel):
    """One camera rendered to a PNG preview (the dashboard's viewer)."""

    model_config = STRICT

    camera: Camera
    frame: Literal["world", "source"] = Field(
        "world",
        description="the camera's frame: the normalised world (the dashboard's) or the dataset's "
        "own",
    )
    width: StrictInt = Field(160, ge=8, le=MAX_VIEW_SIDE, description="image width in pixels")
    height: StrictInt = Field(120, ge=8, le=MAX_VIEW_SIDE, description="image height in pixels")
    appearance: Literal["mean"] | Annotated[StrictInt, Field(ge=0, le=2**31 - 1)] = Field(
        "mean",
        description="'mean' of the training views' appearance embeddings, or a training image's "
        "index",
    )
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

    what: Literal["pointcloud", "cameras", "occupancy"] = Field(
        description="a point cloud of the surfaces, the cameras, or the occupancy's kept cells"
    )
    # pointcloud: expected-depth points of training and validation pixels whose rays are nearly
    # opaque
    stride: StrictInt = Field(
        1, ge=1, le=64, description="every stride-th pixel along rows and columns"
    )
    min_opacity: float = Field(
        0.9, ge=0, le=1, description="a ray's foreground opacity a point needs"
    )
    max_points: StrictInt = Field(
        1_000_000, ge=1, le=20_000_000, description="seeded subsample beyond this"
    )
    # occupancy: the cells of a regular grid over the foreground box that the method's occupancy
    # keeps
    resolution: StrictInt = Field(
        128, ge=8, le=512, description="occupancy: cells per side of the grid"
    )

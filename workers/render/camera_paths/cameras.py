"""cameras: a user's path, one camera per frame or keyframes to interpolate, in the dataset's own
frame (`source`) or the normalised world the API's cameras route and the dashboard's viewer use
(`world`)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

from pydantic import Field, StrictInt, ValidationInfo, field_validator

from workers.render.camera_paths.base import MAX_FRAMES, Camera, PathKind

if TYPE_CHECKING:
    from model.scenes.camera_paths import CameraPath
    from model.scenes.scene import Scene


class CamerasPath(PathKind):
    kind: Literal["cameras"] = "cameras"
    frame: Literal["source", "world"] = Field(
        "source", description="the cameras' frame: the dataset's own or the normalised world"
    )
    width: StrictInt | None = Field(
        None,
        ge=1,
        le=8192,
        description="the size the intrinsics are given at (default: the render's)",
    )
    height: StrictInt | None = Field(
        None, ge=1, le=8192, description="the height the intrinsics are given at"
    )
    interpolate: bool = Field(
        False,
        description="the cameras are keyframes: render `frames` frames through them (evenly along "
        "the path, rotations interpolated); else one frame per camera",
    )
    cameras: list[Camera] = Field(
        min_length=1, max_length=MAX_FRAMES, description="one per frame, or keyframes"
    )

    @field_validator("cameras")
    @classmethod
    def keyframes(cls, cameras: list[Camera], info: ValidationInfo) -> list[Camera]:
        if info.data.get("interpolate") and len(cameras) < 2:
            raise ValueError("interpolating a path needs at least two cameras")
        return cameras

    def frame_count(self) -> int | None:
        return None if self.interpolate else len(self.cameras)

    def build(self, scene: Scene, width: int, height: int, frames: int) -> CameraPath:
        from model.scenes.camera_paths import interpolate, intrinsics_for_fov, user_path

        sx, sy = width / (self.width or width), height / (self.height or height)
        intrinsics = [
            [c.intrinsics[0] * sx, c.intrinsics[1] * sy, c.intrinsics[2] * sx, c.intrinsics[3] * sy]
            if c.intrinsics is not None
            else intrinsics_for_fov(c.fov_deg, width, height).tolist()
            for c in self.cameras
        ]
        norm = scene.normalization if self.frame == "source" else None
        given = user_path(
            [c.c2w for c in self.cameras], intrinsics, width, height, norm, field="path.cameras"
        )
        return interpolate(given, frames) if self.interpolate else given

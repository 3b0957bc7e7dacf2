"""nerfstudio: nerfstudio's camera_path.json (perspective cameras), read in the dataset's own
frame."""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictInt, field_validator

from workers.render.camera_paths.base import MAX_FRAMES, Camera, Finite, PathKind

if TYPE_CHECKING:
    from model.scenes.camera_paths import CameraPath
    from model.scenes.scene import Scene


class NerfstudioFrame(BaseModel):
    model_config = ConfigDict(frozen=True, extra="ignore", allow_inf_nan=False)
    camera_to_world: list[Finite] = Field(
        min_length=16, max_length=16, description="4x4, row by row"
    )
    fov: float = Field(gt=1, lt=170, description="vertical, degrees")

    @field_validator("camera_to_world")
    @classmethod
    def a_rotation_and_a_centre(cls, values: list[float]) -> list[float]:
        Camera.a_rotation_and_a_centre([values[i : i + 4] for i in range(0, 16, 4)])
        return values


class NerfstudioPath(PathKind):
    model_config = ConfigDict(frozen=True, extra="ignore", allow_inf_nan=False)
    kind: Literal["nerfstudio"] = "nerfstudio"
    camera_type: Literal["perspective"] = Field(
        "perspective", description="the one camera model read"
    )
    render_width: StrictInt | None = Field(
        None, ge=1, le=8192, description="its size (default: the render's)"
    )
    render_height: StrictInt | None = Field(
        None, ge=1, le=8192, description="its size (default: the render's)"
    )
    camera_path: list[NerfstudioFrame] = Field(
        min_length=1, max_length=MAX_FRAMES, description="one camera per frame"
    )

    def frame_count(self) -> int | None:
        return len(self.camera_path)

    def build(self, scene: Scene, width: int, height: int, frames: int) -> CameraPath:
        from model.scenes.camera_paths import intrinsics_for_fov, user_path

        c2w = [[f.camera_to_world[i : i + 4] for i in range(0, 16, 4)] for f in self.camera_path]
        intrinsics = [intrinsics_for_fov(f.fov, width, height).tolist() for f in self.camera_path]
        return user_path(
            c2w, intrinsics, width, height, scene.normalization, field="path.camera_path"
        )

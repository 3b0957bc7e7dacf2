"""What every camera-path kind is: a strict pydantic schema with a `kind` tag that builds its path
in the world frame at a render's size (model/camera_paths.CameraPath). `build` imports PyTorch when
called, so the schemas stay light for the API process."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, ClassVar

from pydantic import BaseModel, ConfigDict, Field, field_validator

from model.scenes.rotation import rotation_problem

if TYPE_CHECKING:
    from model.scenes.camera_paths import CameraPath
    from model.scenes.scene import Scene

MAX_FRAMES = 1200

Finite = Annotated[float, Field(ge=-1e9, le=1e9)]
STRICT = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class PathKind(BaseModel):
    model_config = STRICT

    kind: str
    # Made from the scene and the options alone (a render's `frames` sets its length), so `leco
    # render --path KIND` and the dashboard's path menu offer it; a user's path brings its own
    # cameras instead.
    generated: ClassVar[bool] = False

    def frame_count(self) -> int | None:
        """The frames the path itself sets (one per camera of a user's path); None: a render's
        `frames`."""
        return None

    def build(self, scene: Scene, width: int, height: int, frames: int) -> CameraPath:
        """The path in the normalised world frame, at width x height."""
        raise NotImplementedError


class Camera(BaseModel):
    """One camera: a camera-to-world matrix (OpenGL axes: right, up, back, centre; 3x4 or 4x4 row by
    row) and either pinhole intrinsics fx, fy, cx, cy at the path's size or a vertical field of
    view."""

    model_config = STRICT

    c2w: list[Annotated[list[Finite], Field(min_length=4, max_length=4)]] = Field(
        min_length=3, max_length=4, description="camera-to-world, 3x4 or 4x4, row by row"
    )
    intrinsics: (
        Annotated[list[Annotated[float, Field(gt=0, le=1e6)]], Field(min_length=4, max_length=4)]
        | None
    ) = Field(None, description="fx, fy, cx, cy in pixels at the path's size")
    fov_deg: float = Field(
        50.0, gt=1, lt=170, description="vertical field of view, used without intrinsics"
    )

    @field_validator("c2w")
    @classmethod
    def a_rotation_and_a_centre(cls, c2w: list[list[float]]) -> list[list[float]]:
        if len(c2w) == 4 and [float(v) for v in c2w[3]] != [0.0, 0.0, 0.0, 1.0]:
            raise ValueError("the last row of a 4x4 camera-to-world must be 0, 0, 0, 1")
        problem = rotation_problem(c2w)
        if problem is not None:
            raise ValueError(problem)
        return c2w

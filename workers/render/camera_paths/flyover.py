"""flyover: along the training cameras in capture order, smoothed (model/scenes/camera_paths.py
`flyover`)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

from pydantic import Field

from workers.render.camera_paths.base import PathKind

if TYPE_CHECKING:
    from model.scenes.camera_paths import CameraPath
    from model.scenes.scene import Scene


class FlyoverPath(PathKind):
    kind: Literal["flyover"] = "flyover"
    generated = True
    smoothing: float = Field(
        0.05, ge=0, le=1, description="Gaussian sigma as a fraction of the training cameras"
    )
    fov_deg: float | None = Field(
        None, gt=1, lt=170, description="default: the training cameras' median"
    )

    def build(self, scene: Scene, width: int, height: int, frames: int) -> CameraPath:
        from model.scenes.camera_paths import flyover, training_order

        return flyover(
            training_order(scene),
            frames,
            width,
            height,
            fov_deg=self.fov_deg,
            smoothing=self.smoothing,
        )

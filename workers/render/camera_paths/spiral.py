"""spiral: LLFF's render path around the mean training camera (model/scenes/camera_paths.py
`spiral`)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

from pydantic import Field

from workers.render.camera_paths.base import PathKind

if TYPE_CHECKING:
    from model.scenes.camera_paths import CameraPath
    from model.scenes.scene import Scene


class SpiralPath(PathKind):
    kind: Literal["spiral"] = "spiral"
    generated = True
    turns: float = Field(2.0, gt=0, le=10, description="turns of the spiral")
    spread: float = Field(
        1.0, gt=0, le=10, description="radius against the training cameras' spread"
    )
    fov_deg: float | None = Field(
        None, gt=1, lt=170, description="default: the training cameras' median"
    )

    def build(self, scene: Scene, width: int, height: int, frames: int) -> CameraPath:
        from model.scenes.camera_paths import spiral, training_order

        return spiral(
            training_order(scene),
            scene.bounds.aabb,
            frames,
            width,
            height,
            fov_deg=self.fov_deg,
            turns=self.turns,
            spread=self.spread,
        )

"""orbit: around the foreground box's centre, looking at it (model/scenes/camera_paths.py
`orbit`)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

from pydantic import Field, model_validator

from workers.render.camera_paths.base import PathKind

if TYPE_CHECKING:
    from model.scenes.camera_paths import CameraPath
    from model.scenes.scene import Scene

MIN_ALTITUDE_PITCH_DEG = 1.0  # an orbit at an altitude is at most 57x that altitude from the box


class OrbitPath(PathKind):
    kind: Literal["orbit"] = "orbit"
    generated = True
    pitch_deg: float = Field(30.0, ge=0, le=89, description="below the horizon")
    altitude: float | None = Field(
        None,
        gt=0,
        le=1e7,
        description="above the foreground box's centre, in the dataset's units (metres where it "
        "has them); default: the box fills the view",
    )
    turns: float = Field(1.0, gt=0, le=10, description="times around the box")
    fov_deg: float = Field(50.0, gt=1, lt=170, description="vertical field of view")

    @model_validator(mode="after")
    def altitude_needs_a_pitch(self) -> OrbitPath:
        # The orbit's distance is altitude / sin(pitch): at a level pitch no distance reaches that
        # altitude.
        if self.altitude is not None and self.pitch_deg < MIN_ALTITUDE_PITCH_DEG:
            raise ValueError(
                f"an orbit at an altitude needs pitch_deg >= {MIN_ALTITUDE_PITCH_DEG:g} (the "
                "camera looks down at the box from altitude / sin(pitch)); got "
                f"pitch_deg={self.pitch_deg:g} with altitude={self.altitude:g}: raise the pitch or "
                "leave the altitude out"
            )
        return self

    def build(self, scene: Scene, width: int, height: int, frames: int) -> CameraPath:
        from model.scenes.camera_paths import orbit

        altitude = None if self.altitude is None else self.altitude / scene.normalization.scale
        return orbit(
            scene.bounds.aabb,
            frames,
            width,
            height,
            fov_deg=self.fov_deg,
            pitch_deg=self.pitch_deg,
            altitude=altitude,
            turns=self.turns,
        )

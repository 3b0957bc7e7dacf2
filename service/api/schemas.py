"""Request and response bodies. A job request IS the training job schema
(workers.config.TrainConfig) plus the scene it trains: one schema from the API down to the loop."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictInt, field_validator

from workers.config import TrainConfig

NAME = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$"


def id_like_name(name: str) -> str | None:
    """Why a scene name is refused though it matches NAME: digits alone read as an id wherever a
    scene is referenced (`/v1/scenes/46`, `{"scene": "46"}`), so such a name would reach, or delete,
    another scene."""
    if name.isascii() and name.isdigit():
        return (
            f"scene name {name!r} is all digits, which reads as a scene id wherever scenes are "
            "referenced: add a letter or a dash (e.g. 'scene-" + name + "')"
        )
    return None


class SyntheticSceneRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str | None = Field(None, pattern=NAME, description="default: <preset>-<seed>")
    preset: Literal["tiny", "city", "village", "large"] = "city"
    seed: StrictInt = Field(0, ge=0, le=2**31 - 1)

    @field_validator("name")
    @classmethod
    def not_an_id(cls, name: str | None) -> str | None:
        reason = id_like_name(name) if name is not None else None
        if reason:
            raise ValueError(reason)
        return name


class SceneOut(BaseModel):
    id: int
    name: str
    source: str
    state: str
    format: str | None
    cameras: int | None
    bounds: dict | None
    generator: dict | None
    error: str | None
    created_at: datetime
    poses_job: int | None = Field(
        None, description="the job finding its poses, for a scene registered from photos"
    )


class JobRequest(TrainConfig):
    """A job: the scene (id or name) and the training config. Unknown fields are refused."""

    scene: Annotated[StrictInt, Field(ge=1, le=2**31 - 1)] | Annotated[str, Field(pattern=NAME)] = (
        Field(description="scene id or name")
    )

    def train_config(self) -> TrainConfig:
        return TrainConfig.model_validate(self.model_dump(exclude={"scene"}))


class PhaseOut(BaseModel):
    name: str
    state: str
    step: int
    steps_total: int
    started_at: datetime | None
    finished_at: datetime | None


class JobOut(BaseModel):
    id: int
    kind: str = Field(
        description="a registered job kind (GET /v1/job-kinds): train, or render / export of the "
        "finished training job `parent_id`"
    )
    trains: bool = Field(
        description="a job of a kind that trains networks: renders, exports and views are made of "
        "it once it succeeded"
    )
    parent_id: int | None
    scene_id: int
    state: str
    method: str
    profile: str
    config: dict
    phase: str | None
    step: int
    total_steps: int
    percent: float
    eta_s: float | None
    rays_per_s: float | None
    attempts: int
    cancel_requested: bool
    error: str | None
    submitted_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    phases: list[PhaseOut]
    latest_metrics: dict[str, dict[str, float]] = Field(
        description="per phase: metric name -> value at its latest step"
    )


class JobList(BaseModel):
    items: list[JobOut]
    total: int
    limit: int
    offset: int
    next_offset: int | None


class Point(BaseModel):
    step: int
    value: float
    wall_time_s: float | None


class Series(BaseModel):
    phase: str
    name: str
    points: list[Point]
    total_points: int = Field(description="points after `after_step`, before downsampling")


class MetricsOut(BaseModel):
    job_id: int
    series: list[Series]


class ArtifactOut(BaseModel):
    id: int
    job_id: int
    phase: str | None
    kind: str
    step: int | None
    name: str
    size: int
    sha256: str
    content_type: str
    created_at: datetime
    url: str

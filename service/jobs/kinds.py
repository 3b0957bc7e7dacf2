"""Every kind of job the service runs, by name: the API, the queue, the dispatchers and the
dashboard read this table and compare no kind names. Adding a kind is a file in this package (its
work: what one attempt does) and one line here (its JobKind). Nothing here imports PyTorch; the work
loads where an attempt runs."""

from __future__ import annotations

import importlib
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

from pydantic import BaseModel

from model.errors import InvalidInput
from model.memory_estimate import estimate_frames_bytes
from model.methods import get_method
from workers.config import TrainConfig
from workers.poses.settings import STAGE_STEPS, STAGES, PosesConfig
from workers.render.schemas import (
    EXPORT_PHASE,
    RENDER_PHASE,
    ExportConfig,
    RenderConfig,
    ViewRequest,
)

if TYPE_CHECKING:
    from service.jobs.context import Attempt


class Refused(InvalidInput):
    """A job of this kind cannot be made of this parent: `field` names the request's field at
    fault."""

    def __init__(self, field: str, message: str):
        super().__init__(message)
        self.field = field


@dataclass(frozen=True)
class Parent:
    """What a kind made of a finished training job may check and size itself by."""

    job_id: int  # the finished training job
    method: str  # its method
    images: int  # its scene's training images
    views: int  # its scene's training and validation views
    config: TrainConfig | None = None  # its config (its profile sizes the networks)
    largest_view: int = 0  # pixels of its scene's largest training or validation view, as trained


@dataclass(frozen=True)
class Memory:
    """A job's estimated peak bytes (model/memory_estimate.py), with the request's field that
    drives it most: the API refuses the job when it exceeds the slot's memory."""

    field: str
    estimate: dict  # {"parts": ..., "total": ...}


@dataclass(frozen=True)
class JobKind:
    name: str
    config: type[BaseModel]  # the job's config: the API's request body, down to the work
    # What one attempt does, given an Attempt (service/jobs/context.py): the function, or
    # "module:function" to import it where an attempt runs (the built-in kinds' work loads PyTorch;
    # the API never imports it).
    work: str | Callable[[Attempt], None]
    # (phase, steps) of a new job, in order; `parent` is None for a kind made of a scene
    phases: Callable[[BaseModel, Parent | None], list[tuple[str, int]]]
    # a step's rays, for the ETA
    rays_per_step: Callable[[BaseModel], int | None] = lambda cfg: None
    # The collection under a training job that submits and lists jobs of this kind (POST
    # /v1/jobs/{id}/renders); None: submitted on a scene (POST /v1/jobs).
    route: str | None = None
    trains: bool = False  # its finished jobs hold networks that other kinds and views are made of
    check: Callable[[BaseModel, Parent], None] = lambda cfg, parent: None  # raises Refused
    # its peak memory, for the API's check against the slot (None: not estimated)
    memory: Callable[[BaseModel, Parent], Memory | None] = lambda cfg, parent: None
    description: str = ""  # of its submit route, in the OpenAPI document
    # the method and profile a job on a scene is listed under (a kind made of a training job
    # inherits its parent's)
    labels: Callable[[BaseModel], tuple[str, str]] = lambda cfg: own_labels(cfg)
    # where a job of a kind with its own submit route is submitted (the API's job-kind list)
    submitted_at: str | None = None
    # the states of its scene a queued job waits for before a dispatcher claims it
    scene_states: tuple[str, ...] = ("ready",)
    # its 422s
    refusals: str = "the job has not succeeded or is not a training job; an invalid body"

    def config_of(self, data: dict) -> BaseModel:
        return self.config.model_validate(data)

    def load_work(self) -> Callable[[Attempt], None]:
        if not isinstance(self.work, str):
            return self.work
        module, _, name = self.work.partition(":")
        return getattr(importlib.import_module(module), name)


KINDS: dict[str, JobKind] = {}


def own_labels(cfg: BaseModel) -> tuple[str, str]:
    """A training config's method and profile."""
    data = cfg.model_dump()
    return str(data["method"]), str(data["profile"])


def register(kind: JobKind) -> JobKind:
    if not re.fullmatch(r"[a-z][a-z0-9-]{0,15}", kind.name):
        raise ValueError(
            f"job kind {kind.name!r}: a name is 1-16 lowercase letters, digits and dashes"
        )
    known = KINDS.get(kind.name)
    if known is not None and known != kind:
        raise ValueError(f"job kind {kind.name!r} is already registered")
    KINDS[kind.name] = kind
    return kind


def get_kind(name: str) -> JobKind:
    if name not in KINDS:
        raise ValueError(f"unknown job kind {name!r}: choose one of {', '.join(KINDS)}")
    return KINDS[name]


def training_phases(cfg: BaseModel, parent: Parent | None) -> list[tuple[str, int]]:
    assert isinstance(cfg, TrainConfig)
    return [(phase, cfg.phase_steps(phase)) for phase in cfg.phases]


def training_rays(cfg: BaseModel) -> int | None:
    assert isinstance(cfg, TrainConfig)
    return cfg.global_batch


def render_phases(cfg: BaseModel, parent: Parent | None) -> list[tuple[str, int]]:
    assert isinstance(cfg, RenderConfig)
    return [(RENDER_PHASE, cfg.frame_count)]


def frame_rays(cfg: BaseModel) -> int | None:
    assert isinstance(cfg, RenderConfig)
    return cfg.width * cfg.height


def check_appearance(appearance: str | int, images: int) -> None:
    """A render's or a view's appearance: 'mean' or one of the training images' embeddings."""
    if appearance != "mean" and int(appearance) >= images:
        raise Refused(
            "appearance",
            f"training image {appearance} does not exist: the job's scene has {images} training "
            f"images (0 to {images - 1}), or use 'mean'",
        )


def appearance_exists(cfg: BaseModel, parent: Parent) -> None:
    assert isinstance(cfg, RenderConfig)
    check_appearance(cfg.appearance, parent.images)


def frames_memory(parent: Parent, field: str, pixels: int, points: int = 0) -> Memory | None:
    if parent.config is None:
        return None
    cfg = parent.config
    estimate = estimate_frames_bytes(
        cfg.method, cfg.resolved_profile(), parent.images or 1, pixels, points
    )
    return Memory(field, estimate)


def render_memory(cfg: BaseModel, parent: Parent) -> Memory | None:
    assert isinstance(cfg, RenderConfig)
    return frames_memory(parent, "width", cfg.width * cfg.height)


def view_memory(cfg: BaseModel, parent: Parent) -> Memory | None:
    """A view (POST /v1/jobs/{id}/view) is one frame, estimated as a render's is."""
    assert isinstance(cfg, ViewRequest)
    return frames_memory(parent, "width", cfg.width * cfg.height)


def export_memory(cfg: BaseModel, parent: Parent) -> Memory | None:
    """A point cloud renders every view at its stride and keeps up to max_points; the cameras and
    the occupancy (queried a chunk of cells at a time) need no more than the networks."""
    assert isinstance(cfg, ExportConfig)
    if cfg.what != "pointcloud":
        return frames_memory(parent, "what", 0)
    pixels = -(-parent.largest_view // cfg.stride**2)
    points = min(cfg.max_points, pixels * parent.views)
    return frames_memory(parent, "stride", pixels, points)


def export_phases(cfg: BaseModel, parent: Parent | None) -> list[tuple[str, int]]:
    assert isinstance(cfg, ExportConfig) and parent is not None
    return [(EXPORT_PHASE, parent.views if cfg.what == "pointcloud" else 1)]


def occupancy_exists(cfg: BaseModel, parent: Parent) -> None:
    assert isinstance(cfg, ExportConfig)
    if cfg.what == "occupancy" and not get_method(parent.method).has_occupancy:
        raise Refused(
            "what",
            f"job {parent.job_id}'s method {parent.method!r} learns no occupancy: there is none to "
            "export (pointcloud and cameras are)",
        )


# POST /v1/jobs submits this one (its body is a TrainConfig and the scene); the others are made of
# its jobs.
TRAIN = register(
    JobKind(
        "train",
        TrainConfig,
        "service.jobs.train:train",
        training_phases,
        training_rays,
        trains=True,
    )
)
register(
    JobKind(
        "render",
        RenderConfig,
        "service.jobs.render:render",
        render_phases,
        frame_rays,
        route="renders",
        check=appearance_exists,
        memory=render_memory,
        description="A video of a finished training job along a camera path: a render job, queued "
        "and run by a dispatcher (progress, cancel and artifacts as for any job: "
        "`video.mp4`, `video.poster.png`, ...).",
        refusals="the job has not succeeded or is not a training job; a bad path, size or frame "
        "count",
    )
)
register(
    JobKind(
        "export",
        ExportConfig,
        "service.jobs.export:export",
        export_phases,
        route="exports",
        check=occupancy_exists,
        memory=export_memory,
        description="Geometry of a finished training job in the dataset's own frame and units: an "
        "export job whose artifacts are the file (pointcloud.ply, cameras.json or "
        "occupancy.ply), transform.json and export.json.",
        refusals="the job has not succeeded or is not a training job; an occupancy its method "
        "lacks",
    )
)


def poses_phases(cfg: BaseModel, parent: Parent | None) -> list[tuple[str, int]]:
    """The pipeline's stages, each counted in percent."""
    return [(stage, STAGE_STEPS) for stage in STAGES]


def poses_labels(cfg: BaseModel) -> tuple[str, str]:
    assert isinstance(cfg, PosesConfig)
    return "colmap", cfg.mapper


# POST /v1/scenes/photos makes one with the scene it poses: its photos become a scene with poses.
POSES = register(
    JobKind(
        "poses",
        PosesConfig,
        "service.jobs.poses:poses",
        poses_phases,
        labels=poses_labels,
        submitted_at="POST /v1/scenes/photos",
        scene_states=("posing",),  # it makes its scene ready
        description="Camera poses for an uploaded archive of photos (COLMAP by pycolmap): "
        "features, matching, mapping, alignment to GPS metres, export; the scene becomes ready "
        "when it succeeds.",
    )
)

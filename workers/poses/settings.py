"""The one schema of a poses job, from `leco scene poses` and the API's request down to the
pipeline (no PyTorch, no pycolmap: the API imports it)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

# The pipeline's stages in order (pipeline.py); a poses job's phases, each counted in percent.
STAGES = ("features", "matching", "mapping", "alignment", "export")
STAGE_STEPS = 100
# Photo formats the pipeline reads (COLMAP reads them too); other files in the folder are skipped.
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


class PosesConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    max_image_size: int = Field(
        1024,
        ge=64,
        le=8192,
        description="features are found on each photo resized to at most this many pixels on its "
        "longer side (COLMAP's SiftExtraction.max_image_size); the photos themselves are kept",
    )
    matcher: Literal["auto", "exhaustive", "sequential", "spatial"] = Field(
        "auto",
        description="which image pairs are matched; auto: spatial when the photos carry GPS, "
        "sequential for video frames, exhaustive up to exhaustive_max photos, else sequential",
    )
    exhaustive_max: int = Field(
        150, ge=2, le=2000, description="auto matches every pair up to this many photos"
    )
    sequential_overlap: int = Field(
        10, ge=1, le=200, description="sequential: each photo is matched with this many after it"
    )
    spatial_neighbors: int = Field(
        30, ge=2, le=500, description="spatial: each photo is matched with its nearest this many"
    )
    mapper: Literal["incremental", "global"] = Field(
        "incremental",
        description="COLMAP's incremental mapper, or its global one (GLOMAP: no progress within "
        "the stage, no cancelling inside it)",
    )
    camera_model: Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"] = Field(
        "SIMPLE_RADIAL",
        description="the COLMAP camera model of every camera; photos of one size and one camera "
        "share one set of intrinsics",
    )
    min_photos: int = Field(5, ge=2, le=1000, description="fewer photos are refused")
    min_registered: float = Field(
        0.5,
        gt=0.0,
        le=1.0,
        description="the share of the photos the kept model must register; under it the run is "
        "refused, saying how many registered",
    )
    gps: Literal["auto", "off"] = Field(
        "auto",
        description="auto: with EXIF GPS on at least 3 registered photos, the model is aligned to "
        "local east-north-up metres; off: the cameras' own frame and scale",
    )
    gps_max_error_m: float = Field(
        10.0,
        gt=0.0,
        le=1000.0,
        description="a photo whose GPS position is further than this from the aligned camera is "
        "an outlier of the GPS alignment",
    )
    seed: int = Field(0, ge=0, le=2**31 - 1, description="COLMAP's random seed")
    threads: int = Field(-1, ge=-1, le=256, description="COLMAP's threads (-1: every core)")
    time_limit_s: float | None = Field(
        None, gt=0, description="the whole run is stopped after this many seconds"
    )
    memory_limit_mb: int | None = Field(
        None,
        ge=256,
        description="the pycolmap process's address space limit; over it the run fails saying so",
    )

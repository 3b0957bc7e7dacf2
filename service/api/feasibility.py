"""Submit-time checks that a training job can run where it would, from what the API already knows
(the scene row's image sizes, the service's backend): a job accepted with 201 never fails on a
batch larger than the scene's pixels or on workers the backend cannot start."""

from __future__ import annotations

from fastapi import HTTPException

from service.settings import Settings
from workers.config import TrainConfig


def largest_image_pixels(info: dict, split: str, downscale: int | None) -> int | None:
    """An upper bound on the pixels of the split's largest image at a job's downscale, from the
    sizes the scene row records (None when the row has none). Sizes are recorded at the scene's own
    scale; a job's factor applies to the full images, each side floored as the loader does."""
    sizes = ((info.get("splits") or {}).get(split) or {}).get("image_sizes")
    if not sizes:
        return None
    base = info.get("downscale") or 1
    largest = 0
    for size in sizes:
        width, height = (int(x) for x in size.split("x"))
        if downscale is not None:
            # the full image is at most (side + 1) * base - 1 pixels on a side
            width = max(1, ((width + 1) * base - 1) // downscale)
            height = max(1, ((height + 1) * base - 1) // downscale)
        largest = max(largest, width * height)
    return largest


def training_pixels_at_most(info: dict, downscale: int | None) -> int | None:
    """An upper bound on the pixels of the training split at the job's downscale."""
    largest = largest_image_pixels(info, "train", downscale)
    return None if largest is None else info["splits"]["train"]["images"] * largest


def check_feasible(cfg: TrainConfig, settings: Settings, scene_name: str, info: dict) -> None:
    """422 naming the fields when the job cannot start here: more workers than the local backend
    runs, or a step's batch larger than the scene's training pixels."""
    problems = []
    if settings.backend == "local" and cfg.workers > 1:
        problems.append(
            {
                "loc": ["body", "workers"],
                "type": "value_error",
                "msg": f"{cfg.workers} workers asked for; this service trains with the local "
                "backend, one worker a job (LECO_BACKEND=ray runs more)",
            }
        )
    pixels = training_pixels_at_most(info, cfg.downscale)
    batch = cfg.global_batch
    if pixels is not None and batch > pixels:
        scale = f"at downscale {cfg.downscale}" if cfg.downscale else "at its own scale"
        problems.append(
            {
                "loc": ["body", "downscale" if cfg.downscale else "overrides"],
                "type": "value_error",
                "msg": f"a step takes {batch} rays ({batch // cfg.workers} per worker, "
                f"rays_per_device, x {cfg.workers}) and scene {scene_name!r} has at most "
                f"{pixels} training pixels {scale}: lower rays_per_device or downscale",
            }
        )
    if problems:
        raise HTTPException(422, problems)

"""Submit-time checks that a training job can run where it would, from what the API already knows
(the scene row's image sizes, or a generating synthetic scene's preset; the service's backend and
its GPUs): a job accepted with 201 never fails on a batch larger than the scene's pixels or on
workers or GPUs the backend cannot start."""

from __future__ import annotations

import os
from pathlib import Path

from fastapi import HTTPException

from model.scenes.folders import folder_factor
from service.settings import Settings
from service.tables import Scene
from workers.config import TrainConfig
from workers.toolchain import cpp_compiler

NVIDIA_GPUS = Path("/proc/driver/nvidia/gpus")  # one folder a GPU the driver sees


def scene_sizes(scene: Scene | None) -> dict:
    """The scene info a job is checked against: the row's, or while a synthetic scene generates,
    the sizes its preset will give it (model/scenes/synthetic/presets.py). A scene still generating
    whose sizes cannot be known is refused with 409 naming its state, as a failed scene is: its
    job could not be checked before it is accepted."""
    if scene is None:
        return {}
    if scene.state == "posing":
        raise HTTPException(
            409,
            f"scene {scene.name!r} is posing (its poses job has not finished): submit the job "
            "once the scene is ready",
        )
    info = scene.info or {}
    if info.get("splits") or scene.state != "generating":
        return info
    from model.scenes.synthetic.presets import PRESETS  # plain data: no PyTorch

    preset = PRESETS.get(str((scene.generator or {}).get("preset")))
    if preset is None:
        raise HTTPException(
            409,
            f"scene {scene.name!r} is generating and its image sizes are not known yet: submit "
            "the job once it is ready",
        )
    return preset.split_info()


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


def recorded_factor(info: dict, downscale: int | None) -> int | None:
    """The factor the loader divides the recorded images' sides by at a job's downscale, or None
    when it reads other files than those recorded (an LLFF folder of another factor). The row
    records the images as the scene loads without a downscale: an LLFF capture from its folder of
    the smallest factor (the row's downscale), any other format at full size."""
    if downscale is None:
        return 1
    base = info.get("downscale") or 1
    if info.get("format") == "llff" or "image_folder_factors" in info:
        factors = info.get("image_folder_factors") or [base]
        if folder_factor(factors, downscale) != base:
            return None
        return downscale // base  # llff.pick_folder: the folder's images, resized by the rest
    return downscale if base == 1 else None


def training_pixels(info: dict, downscale: int | None) -> int | None:
    """The training split's pixels at a job's downscale, exactly as the loader sizes its images
    (model/scenes/images.py downscaled_size: each side floored, at least 1), from the images of each
    size the row records; None for a row without them (registered before they were recorded) or an
    LLFF downscale read from another folder."""
    train = (info.get("splits") or {}).get("train") or {}
    by_size = train.get("images_by_size")
    factor = recorded_factor(info, downscale)
    if not by_size or factor is None:
        return None
    total = 0
    for size, count in by_size.items():
        width, height = (int(x) for x in size.split("x"))
        total += int(count) * max(1, width // factor) * max(1, height // factor)
    return total


def training_pixels_at_most(info: dict, downscale: int | None) -> int | None:
    """The pixels of the training split at the job's downscale: exact where the row records its
    images of each size, else an upper bound (every image as large as the largest)."""
    exact = training_pixels(info, downscale)
    if exact is not None:
        return exact
    largest = largest_image_pixels(info, "train", downscale)
    return None if largest is None else info["splits"]["train"]["images"] * largest


def local_gpus(settings: Settings) -> int:
    """The GPUs of this machine's backend (the embedded Ray, or the local backend's process):
    LECO_LOCAL_GPUS when set, else those the NVIDIA driver lists, as CUDA_VISIBLE_DEVICES narrows
    them (read without PyTorch)."""
    if settings.local_gpus is not None:
        return settings.local_gpus
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        devices = [d for d in visible.split(",") if d.strip()]
        return 0 if devices[:1] in ([], ["-1"], ["NoDevFiles"]) else len(devices)
    try:
        return sum(1 for _ in NVIDIA_GPUS.iterdir())
    except OSError:
        return 0


def check_feasible(cfg: TrainConfig, settings: Settings, scene_name: str, info: dict) -> None:
    """422 naming the fields when the job cannot start here: more workers than the local backend
    runs, more GPU workers than the backend has GPUs, `compile` on CPU workers of a machine with
    no C++ compiler, or a step's batch larger than the scene's training pixels."""
    problems = []

    def problem(field: str, msg: str) -> None:
        problems.append({"loc": ["body", field], "type": "value_error", "msg": msg})

    if settings.backend == "local" and cfg.workers > 1:
        problem(
            "workers",
            f"{cfg.workers} workers asked for; this service trains with the local backend, one "
            "worker a job (LECO_BACKEND=ray runs more)",
        )
    cluster = settings.ray_address is not None
    if cfg.use_gpu and cluster:
        if settings.cluster_gpus is not None and cfg.workers > settings.cluster_gpus:
            problem(
                "use_gpu",
                f"{cfg.workers} GPU workers asked for; this cluster has {settings.cluster_gpus} "
                "GPUs",
            )
    elif cfg.use_gpu:
        gpus = local_gpus(settings)
        where = "local backend" if settings.backend == "local" else "local Ray"
        if gpus == 0:
            problem("use_gpu", f"use_gpu asked for, but this service's {where} has no GPU")
        elif cfg.workers > gpus:
            problem(
                "workers",
                f"{cfg.workers} GPU workers asked for (one GPU each); this service's {where} has "
                f"{gpus} GPU{'s' if gpus > 1 else ''}: ask for at most {gpus} workers or no GPU",
            )
    if cfg.compile and not cfg.use_gpu and not cluster and cpp_compiler() is None:
        # the service's own workers run here: a cluster's workers are other machines
        problem(
            "compile",
            "compile=true needs a C++ compiler on a CPU worker (inductor builds its kernels at run "
            "time) and this service's machine has none: install g++ there, or set compile=false",
        )
    pixels = training_pixels_at_most(info, cfg.downscale)
    batch = cfg.global_batch
    if pixels is not None and batch > pixels:
        exact = training_pixels(info, cfg.downscale) is not None
        scale = f"at downscale {cfg.downscale}" if cfg.downscale else "at its own scale"
        problem(
            "downscale" if cfg.downscale else "overrides",
            f"a step takes {batch} rays ({batch // cfg.workers} per worker, rays_per_device, x "
            f"{cfg.workers}) and scene {scene_name!r} has {'' if exact else 'at most '}{pixels} "
            f"training pixels {scale}: lower rays_per_device or downscale",
        )
    if problems:
        raise HTTPException(422, problems)

"""A video of a finished run along a camera path: `leco render` and the service's render jobs.
Frames are rendered one at a time with the method's own sampler and encoded as they come; the store
(the service's, or none) gets each frame's progress and is asked between frames whether to stop."""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from PIL import Image

from model.scenes.camera_paths import CameraPath, world_to_source_pose
from model.scenes.scene import Scene
from workers.render.frames import appearance_row, render_frame
from workers.render.schemas import RENDER_PHASE, RenderConfig
from workers.render.video import Mp4Writer
from workers.renderer import depth_grey, depth_range, to_uint8
from workers.store import RunStore, check_stop
from workers.trained import Trained

SIBLINGS = {
    "depth": ".depth.mp4",
    "poster": ".poster.png",
    "path": ".camera_path.json",
    "summary": ".render.json",
}


def outputs(video: Path) -> dict[str, Path]:
    """The files a render writes: the video and, beside it under its stem, the rest."""
    video = Path(video)
    return {
        "video": video,
        **{k: video.with_name(video.stem + suffix) for k, suffix in SIBLINGS.items()},
    }


def build_path(cfg: RenderConfig, scene: Scene) -> CameraPath:
    """The path in the world frame, at the render's size (its kind builds it:
    workers/camera_paths)."""
    return cfg.path.build(scene, cfg.width, cfg.height, cfg.frames)


def path_in_source_frame(path: CameraPath, scene: Scene) -> dict:
    """The rendered path as a `cameras` path in the dataset's own frame: a file `--path` takes
    again."""
    scale = scene.normalization.scale
    return {
        "kind": "cameras",
        "frame": "source",
        "units": scene.normalization.units,
        "width": path.width,
        "height": path.height,
        "cameras": [
            {"c2w": world_to_source_pose(c, scene.normalization).tolist(), "intrinsics": k.tolist()}
            for c, k in zip(path.c2w, path.intrinsics)
        ],
        "note": "OpenGL camera axes (right, up, back); the world frame is the dataset's frame "
        f"moved and scaled by 1/{scale:g}",
    }


def render_video(
    trained: Trained,
    cfg: RenderConfig,
    video: Path,
    store: RunStore | None = None,
    log: Callable[[str], None] = lambda text: None,
) -> dict:
    """Writes `video` (an H.264 MP4) and beside it NAME.poster.png (the first frame),
    NAME.camera_path.json (the path in the dataset's frame), NAME.render.json (timings) and, when
    asked, NAME.depth.mp4."""
    files = outputs(video)
    files["video"].parent.mkdir(parents=True, exist_ok=True)
    path = build_path(cfg, trained.scene)
    cameras = path.cameras()
    row = appearance_row(trained, cfg.appearance)
    writers = [Mp4Writer(files["video"], cfg.width, cfg.height, cfg.fps)]
    if cfg.depth_video:
        writers.append(Mp4Writer(files["depth"], cfg.width, cfg.height, cfg.fps))
    seconds: list[float] = []
    samples: list[float] = []
    near_far = (0.0, 1.0)
    if store is not None:
        store.phase_started(RENDER_PHASE)
    try:
        for i in range(len(path)):
            check_stop(store)
            started = time.perf_counter()
            frame = render_frame(trained, cameras, i, row)
            seconds.append(time.perf_counter() - started)
            samples.append(frame.samples_per_ray)
            writers[0].write(to_uint8(frame.rgb).numpy())
            if i == 0:  # the first frame's depth range holds for the whole video
                Image.fromarray(to_uint8(frame.rgb).numpy()).save(files["poster"])
                near_far = depth_range(frame)
            if cfg.depth_video:
                writers[1].write(depth_grey(frame, *near_far).numpy())
            if store is not None:
                store.write(
                    i + 1,
                    {
                        "phase": RENDER_PHASE,
                        "phase_step": i + 1,
                        "seconds_per_frame": seconds[-1],
                        "rays_per_s": cfg.width * cfg.height / seconds[-1],
                        "samples_per_ray": frame.samples_per_ray,
                    },
                )
            log(f"frame {i + 1}/{len(path)}: {seconds[-1]:.2f} s")
        for writer in writers:
            writer.close()
    except BaseException:
        for writer in writers:
            writer.abort()
        raise
    files["path"].write_text(json.dumps(path_in_source_frame(path, trained.scene), indent=1))
    summary = {
        "method": trained.cfg.method,
        "profile": trained.cfg.profile,
        "path": cfg.path.kind,
        "frames": len(path),
        "width": cfg.width,
        "height": cfg.height,
        "fps": cfg.fps,
        "device": str(trained.device),
        "appearance": (
            "mean of the training views' embeddings"
            if cfg.appearance == "mean"
            else f"training image {cfg.appearance} "
            f"({trained.scene.train.names[int(cfg.appearance)]})"
        ),
        "seconds_per_frame": statistics.fmean(seconds),
        "median_seconds_per_frame": statistics.median(seconds),
        "seconds_total": sum(seconds),
        "rays_per_s": cfg.width * cfg.height * len(seconds) / sum(seconds),
        "samples_per_ray": float(np.mean(samples)),
        "threads": torch.get_num_threads(),
        "files": [files[k].name for k in ("video", "poster", "path", "summary")]
        + ([files["depth"].name] if cfg.depth_video else []),
    }
    files["summary"].write_text(json.dumps(summary, indent=1))
    return summary

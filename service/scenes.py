"""Registering scenes: a synthetic city from its generator parameters (generated in a background
thread, never in the request), or an uploaded archive validated with the loaders' own checks before
anything is stored. A scene folder appears under the scenes root complete, or not at all."""

from __future__ import annotations

import json
import logging
import shutil
import tempfile
import threading
from pathlib import Path
from typing import TYPE_CHECKING

from sqlalchemy import select
from sqlalchemy.orm import Session

from model.errors import Conflict
from service.db import transaction
from service.settings import Settings
from service.tables import Scene
from service.workpool import WorkPool
from workers.poses.settings import PosesConfig

if TYPE_CHECKING:
    from model.scenes.scene import Scene as LoadedScene

log = logging.getLogger("leco.scenes")


class SceneConflict(Conflict):
    pass


# ----- the heavy parts: module-level functions of plain data, run in the scene pool's processes
# -----------
def load_within_budget(
    path: Path, max_pixels: int, source: str = "LECO_MAX_SCENE_PIXELS"
) -> LoadedScene:
    """The scene at `path`, read from its image headers (nothing is decoded), its pixels counted
    against the per-scene budget (`source` names it): a registration is as fast for 2,000 photos as
    for 20."""
    from model.scenes import load_scene
    from model.scenes.limits import pixel_budget

    with pixel_budget(max_pixels, source):
        return load_scene(path)


def describe_folder(
    path: Path, max_pixels: int, source: str = "LECO_MAX_SCENE_PIXELS"
) -> tuple[dict, dict]:
    """The scene's summary for its row and its camera layout (for /cameras), from one load."""
    from model.scenes.info import describe

    scene = load_within_budget(path, max_pixels, source)
    return describe(scene), camera_layout(scene)


# Real captures and renders hold at most a few decoded pixels per byte of PNG or JPEG (lego 1.0 on
# average and 1.6 in its densest image, fern 0.6, the synthetic city 0.5): an archive may declare at
# most this many, so a small upload cannot register a scene that later decodes to gigabytes (1 MiB:
# at most one 4096 x 4096 image's worth of pixels, 48 MB as RGB; decoding it grows a process by well
# under 256 MB, tests/model/scenes/test_decode_memory.py).
MAX_PIXELS_PER_UPLOAD_BYTE = 16


def upload_pixel_budget(max_scene_pixels: int, archive_bytes: int) -> tuple[int, str]:
    """The pixels an upload of `archive_bytes` may decode, and what sets that budget."""
    by_size = MAX_PIXELS_PER_UPLOAD_BYTE * archive_bytes
    if by_size < max_scene_pixels:
        return (
            by_size,
            f"{MAX_PIXELS_PER_UPLOAD_BYTE} pixels per byte of the {archive_bytes:,}-byte upload",
        )
    return max_scene_pixels, "LECO_MAX_SCENE_PIXELS"


def read_upload(archive: Path, dest: Path, max_pixels: int) -> tuple[Path, dict, dict]:
    """Extracts the archive into `dest` and loads the scene: its root folder, summary and camera
    layout."""
    from service.archives import extract_archive

    budget, source = upload_pixel_budget(max_pixels, archive.stat().st_size)
    root = extract_archive(archive, dest)
    return (root, *describe_folder(root, budget, source))


def generate_folder(preset: str, seed: int, path: Path, max_pixels: int) -> tuple[dict, dict]:
    from model.scenes.synthetic import generate

    # generation is deterministic and atomic: a finished folder is the same scene
    if not path.exists():
        generate(preset, seed, path)
    return describe_folder(path, max_pixels)


def layout_of(path: Path, max_pixels: int) -> dict:
    return camera_layout(load_within_budget(path, max_pixels))


# ----- in the API process: rows, files and the pool
# ---------------------------------------------------------
def camera_layout(scene: LoadedScene) -> dict:
    cameras = []
    for split, views in scene.splits.items():
        for center, forward in zip(views.cameras.centers.tolist(), views.cameras.forward.tolist()):
            cameras.append({"split": split, "center": center, "forward": forward})
    return {
        "frame": "normalised world (z up)",
        "aabb": scene.bounds.aabb.tolist(),
        "cameras": cameras,
    }


def layout_path(settings: Settings, scene_id: int) -> Path:
    """Beside the scene's folder, not in it: the folder stays exactly what the user uploaded."""
    return settings.scenes_dir / f"scene-{scene_id}.cameras.json"


def write_layout(path: Path, layout: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(layout))
    tmp.replace(path)


def read_layout(settings: Settings, scene_id: int, path: Path, pool: WorkPool) -> dict:
    """The layout written at registration; a scene registered before layouts were written is loaded
    once (within the pixel budget, in the pool; the caller holds a running place) and its layout
    kept."""
    target = layout_path(settings, scene_id)
    if not target.is_file():
        write_layout(target, pool.call(layout_of, path, settings.max_scene_pixels))
    return json.loads(target.read_text())


def refuse_taken(session: Session, name: str) -> None:
    if session.scalar(select(Scene.id).where(Scene.name == name)) is not None:
        raise SceneConflict(
            f"a scene named {name!r} already exists: choose another name or delete it first"
        )


def _new_row(settings: Settings, name: str, source: str, state: str, **fields: object) -> int:
    with transaction(settings.db_url) as session:
        refuse_taken(session, name)
        row = Scene(name=name, source=source, state=state, path="", **fields)
        session.add(row)
        session.flush()
        row.path = str(settings.scenes_dir / f"scene-{row.id}")
        return row.id


def register_synthetic(
    settings: Settings, name: str, preset: str, seed: int, pool: WorkPool
) -> int:
    """Raises Busy when the scene pool is full (before anything is stored) or SceneConflict."""
    pool.admit()
    try:
        scene_id = _new_row(
            settings,
            name,
            "synthetic",
            "generating",
            generator={"preset": preset, "seed": seed},
            format="meganerf",
        )
    except BaseException:
        pool.release()
        raise
    start_generation(settings, scene_id, pool, admitted=True)
    return scene_id


def start_generation(
    settings: Settings, scene_id: int, pool: WorkPool, admitted: bool
) -> threading.Thread:
    thread = threading.Thread(
        target=_generate,
        args=(settings, scene_id, pool, admitted),
        daemon=True,
        name=f"leco-scene-{scene_id}",
    )
    thread.start()
    return thread


def _generate(settings: Settings, scene_id: int, pool: WorkPool, admitted: bool) -> None:
    if not admitted:
        pool.admit(wait=True)
    try:
        with pool.running():
            _generate_now(settings, scene_id, pool)
    finally:
        pool.release()


def _generate_now(settings: Settings, scene_id: int, pool: WorkPool) -> None:
    with transaction(settings.db_url) as session:
        row = session.get(Scene, scene_id)
        # The API refuses to delete a scene while it is generating, and synthetic scenes always have
        # a generator.
        if row is None or row.generator is None:
            raise RuntimeError(f"scene {scene_id}: no row with a generator to generate it from")
        path, generator = Path(row.path), dict(row.generator)
    try:
        info, layout = pool.call(
            generate_folder,
            generator["preset"],
            int(generator["seed"]),
            path,
            settings.max_scene_pixels,
        )
        write_layout(layout_path(settings, scene_id), layout)
        state, error = "ready", None
    except Exception as exc:
        log.exception("scene %s: generation failed", scene_id)
        info, state, error = None, "failed", f"{type(exc).__name__}: {exc}"
    with transaction(settings.db_url) as session:
        row = session.get(Scene, scene_id)
        if row is not None:
            row.state, row.info, row.error = state, info, error


def resume_generation(settings: Settings, pool: WorkPool) -> list[int]:
    """Scenes left 'generating' by a process that stopped: generate them again (through the pool,
    waiting for places in their own threads)."""
    with transaction(settings.db_url) as session:
        ids = list(session.scalars(select(Scene.id).where(Scene.state == "generating")))
    for scene_id in ids:
        start_generation(settings, scene_id, pool, admitted=False)
    return ids


def register_upload(settings: Settings, name: str, archive: Path, pool: WorkPool) -> int:
    """Extracts and loads the archive in a scratch folder (in the pool's process); only a scene that
    loads is moved into place and gets a row. Raises ArchiveError / SceneError (the user's archive),
    WorkerLost or SceneConflict (the name). The caller holds a running place in the scene pool."""
    with transaction(settings.db_url) as session:
        refuse_taken(session, name)
    settings.scenes_dir.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(dir=settings.scenes_dir, prefix=".upload-"))
    try:
        root, info, layout = pool.call(
            read_upload, archive, scratch / "x", settings.max_scene_pixels
        )
        scene_id = _new_row(settings, name, "upload", "ready", format=info["format"], info=info)
        target = settings.scenes_dir / f"scene-{scene_id}"
        try:
            write_layout(layout_path(settings, scene_id), layout)
            root.rename(target)
        except OSError:
            layout_path(settings, scene_id).unlink(missing_ok=True)
            with transaction(settings.db_url) as session:
                session.delete(session.get(Scene, scene_id))
            raise
        return scene_id
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


# ----- photos to pose: an archive of photos becomes a scene once its poses job succeeds
# ---------------
def photos_path(settings: Settings, scene_id: int) -> Path:
    """Where a scene's uploaded photos wait for their poses job, beside the folder the job writes
    (the scene's own, which appears whole when the job succeeds)."""
    return settings.scenes_dir / f"scene-{scene_id}.photos"


def posing_paths(settings: Settings, scene_id: int) -> list[Path]:
    """Everything a scene posed from photos may leave beside its folder: the photos, the pipeline's
    work folder (workers/poses/pipeline.py) and a partial export."""
    return [
        photos_path(settings, scene_id),
        settings.scenes_dir / f".scene-{scene_id}.poses",
        settings.scenes_dir / f".scene-{scene_id}.poses.lock",
        settings.scenes_dir / f".scene-{scene_id}.partial",
    ]


def remove_scene_files(settings: Settings, scene_id: int, path: Path) -> None:
    """A deleted scene's folder, its camera layout and whatever posing left beside it."""
    for target in (path, *posing_paths(settings, scene_id)):
        if target.is_dir():
            shutil.rmtree(target, ignore_errors=True)
        else:
            target.unlink(missing_ok=True)
    layout_path(settings, scene_id).unlink(missing_ok=True)


def extract_photos(archive: Path, dest: Path, min_photos: int) -> tuple[Path, int]:
    """Extracts an archive of photos (in the scene pool's process): the folder and its photos'
    count; fewer than `min_photos` is refused before anything is registered."""
    from model.scenes.errors import SceneError
    from service.archives import extract_archive
    from workers.poses.settings import PHOTO_SUFFIXES

    root = extract_archive(archive, dest)
    count = sum(
        1
        for p in root.rglob("*")
        if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in PHOTO_SUFFIXES
    )
    if count < min_photos:
        shutil.rmtree(dest, ignore_errors=True)
        raise SceneError(
            "<upload>",
            f"the archive holds {count} photos ({', '.join(PHOTO_SUFFIXES)}); at least "
            f"{min_photos} overlapping photos are needed to find poses (min_photos)",
        )
    return root, count


def register_photos(
    settings: Settings, name: str, archive: Path, config: PosesConfig, pool: WorkPool
) -> tuple[int, int]:
    """An archive of photos becomes a scene in state 'posing' and its poses job (service/jobs/
    poses.py), written together; the photos are moved into place before either is visible to a
    dispatcher. Raises ArchiveError / SceneError (the upload), WorkerLost or SceneConflict. The
    caller holds a running place in the scene pool."""
    from service.jobs.kinds import POSES
    from service.jobs.submit import submit

    with transaction(settings.db_url) as session:
        refuse_taken(session, name)
    settings.scenes_dir.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(dir=settings.scenes_dir, prefix=".upload-"))
    try:
        root, _ = pool.call(extract_photos, archive, scratch / "x", config.min_photos)
        moved: Path | None = None
        try:
            with transaction(settings.db_url) as session:
                refuse_taken(session, name)
                row = Scene(name=name, source="photos", state="posing", path="")
                session.add(row)
                session.flush()
                row.path = str(settings.scenes_dir / f"scene-{row.id}")
                # the photos are in place before the job commits: no dispatcher claims it
                # without them
                moved = photos_path(settings, row.id)
                root.rename(moved)
                job = submit(session, POSES, row.id, config)
                session.flush()
                ids = row.id, job.id
        except BaseException:
            if moved is not None:  # the rows were not written: neither are the photos
                shutil.rmtree(moved, ignore_errors=True)
            raise
        return ids
    finally:
        shutil.rmtree(scratch, ignore_errors=True)

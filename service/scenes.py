"""Registering scenes: a synthetic city from its generator parameters (generated in a background thread,
never in the request), or an uploaded archive validated with the loaders' own checks before anything is
stored. A scene folder appears under the scenes root complete, or not at all."""

from __future__ import annotations

import logging
import shutil
import tempfile
import threading
from pathlib import Path

from sqlalchemy import select

from service.db import transaction
from service.settings import Settings
from service.tables import Scene

log = logging.getLogger("leco.scenes")


class SceneConflict(ValueError):
    pass


def describe_folder(path: Path) -> dict:
    from model.scenes import load_scene
    from model.scenes.info import describe

    return describe(load_scene(path))


def _new_row(settings: Settings, name: str, source: str, state: str, **fields) -> int:
    with transaction(settings.db_url) as session:
        if session.scalar(select(Scene.id).where(Scene.name == name)) is not None:
            raise SceneConflict(f"a scene named {name!r} already exists: choose another name or delete it first")
        row = Scene(name=name, source=source, state=state, path="", **fields)
        session.add(row)
        session.flush()
        row.path = str(settings.scenes_dir / f"scene-{row.id}")
        return row.id


def register_synthetic(settings: Settings, name: str, preset: str, seed: int) -> int:
    scene_id = _new_row(settings, name, "synthetic", "generating", generator={"preset": preset, "seed": seed},
                        format="meganerf")
    start_generation(settings, scene_id)
    return scene_id


def start_generation(settings: Settings, scene_id: int) -> threading.Thread:
    thread = threading.Thread(target=_generate, args=(settings, scene_id), daemon=True, name=f"leco-scene-{scene_id}")
    thread.start()
    return thread


def _generate(settings: Settings, scene_id: int) -> None:
    from model.scenes.synthetic import generate

    with transaction(settings.db_url) as session:
        row = session.get(Scene, scene_id)
        path, generator = Path(row.path), dict(row.generator)
    try:
        if not path.exists():  # generation is deterministic and atomic: a finished folder is the same scene
            generate(generator["preset"], int(generator["seed"]), path)
        info, state, error = describe_folder(path), "ready", None
    except Exception as exc:
        log.exception("scene %s: generation failed", scene_id)
        info, state, error = None, "failed", f"{type(exc).__name__}: {exc}"
    with transaction(settings.db_url) as session:
        row = session.get(Scene, scene_id)
        if row is not None:
            row.state, row.info, row.error = state, info, error


def resume_generation(settings: Settings) -> list[int]:
    """Scenes left 'generating' by a process that stopped: generate them again."""
    with transaction(settings.db_url) as session:
        ids = list(session.scalars(select(Scene.id).where(Scene.state == "generating")))
    for scene_id in ids:
        start_generation(settings, scene_id)
    return ids


def register_upload(settings: Settings, name: str, archive: Path) -> int:
    """Extracts and loads the archive in a scratch folder; only a scene that loads is moved into place and
    gets a row. Raises ArchiveError / SceneError (the user's archive) or SceneConflict (the name)."""
    from service.archives import extract_archive

    with transaction(settings.db_url) as session:
        if session.scalar(select(Scene.id).where(Scene.name == name)) is not None:
            raise SceneConflict(f"a scene named {name!r} already exists: choose another name or delete it first")
    settings.scenes_dir.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(dir=settings.scenes_dir, prefix=".upload-"))
    try:
        root = extract_archive(archive, scratch / "x")
        info = describe_folder(root)
        scene_id = _new_row(settings, name, "upload", "ready", format=info["format"], info=info)
        target = settings.scenes_dir / f"scene-{scene_id}"
        try:
            root.rename(target)
        except OSError:
            with transaction(settings.db_url) as session:
                session.delete(session.get(Scene, scene_id))
            raise
        return scene_id
    finally:
        shutil.rmtree(scratch, ignore_errors=True)

"""Every file a scene is read from must lie inside the scene's folder once symlinks are followed: a
transforms.json naming `/proc/self/environ` or `../other-scene/x.png`, or a symlink out of the
folder, is refused before anything is opened, with the same message whether the target exists (so a
dataset cannot probe which files the server has)."""

from __future__ import annotations

from pathlib import Path

from model.scenes.errors import SceneError


def inside(root: Path, path: Path, source: Path, what: str) -> Path:
    """`path` itself when it resolves inside `root`; else a SceneError on `source` naming `what`."""
    try:
        contained = path.resolve().is_relative_to(root.resolve())
    # symlink loops, NUL bytes: not a file inside the scene either
    except (OSError, RuntimeError, ValueError):
        contained = False
    if not contained:
        raise SceneError(source, f"{what} points outside the scene folder")
    return path


def named_file(root: Path, named: object, source: Path, what: str) -> Path:
    """root / named for a path the dataset file `source` names in field `what` (relative to
    root)."""
    if not isinstance(named, str):
        kind = type(named).__name__ if named is not None else "null"
        raise SceneError(
            source, f"{what} must be a string (a path relative to the scene), got {kind}"
        )
    text = named
    return inside(root, root / text, source, f"{what} {text[:200]!r}")


def scene_file(root: Path, path: Path) -> Path:
    """A file found by its place in the layout (a glob, a fixed name): refused if a symlink leads
    out."""
    return inside(root, path, path, "this file")

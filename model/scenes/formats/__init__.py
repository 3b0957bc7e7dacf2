"""Scene formats, detected from the files a folder holds."""

from __future__ import annotations

from pathlib import Path

from model.scenes.errors import SceneError

# Marker file -> format, in detection order.
MARKERS = (
    ("coordinates.pt", "meganerf"),
    ("transforms_train.json", "blender"),
    ("transforms.json", "nerfstudio"),
    ("poses_bounds.npy", "llff"),
)
FORMATS = tuple(name for _, name in MARKERS)


def detect_format(root: Path) -> str:
    if not root.exists():
        raise SceneError(root, "scene folder does not exist")
    if not root.is_dir():
        raise SceneError(
            root, "is not a folder (a scene is a folder in one of the supported formats)"
        )
    for marker, name in MARKERS:
        if (root / marker).is_file():
            return name
    present = sorted(p.name for p in root.iterdir())[:10]
    expected = ", ".join(f"{m} ({n})" for m, n in MARKERS)
    raise SceneError(
        root,
        f"unknown scene format: expected one of {expected}; found {present or 'an empty folder'}",
    )

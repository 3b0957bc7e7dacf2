"""Scene formats, detected from the files a folder holds."""

from __future__ import annotations

from pathlib import Path

from model.scenes.errors import SceneError

# Marker files (paths relative to the scene folder, all of them present) -> format, in detection
# order. LLFF comes before COLMAP: an LLFF capture often keeps the COLMAP model it came from.
MARKERS: tuple[tuple[tuple[str, ...], str], ...] = (
    (("coordinates.pt",), "meganerf"),
    (("transforms_train.json",), "blender"),
    (("transforms.json",), "nerfstudio"),
    (("poses_bounds.npy",), "llff"),
    (("sparse/0/cameras.bin", "sparse/0/images.bin"), "colmap"),
    (("sparse/0/cameras.txt", "sparse/0/images.txt"), "colmap"),
)
FORMATS = tuple(dict.fromkeys(name for _, name in MARKERS))


def detect_format(root: Path) -> str:
    if not root.exists():
        raise SceneError(root, "scene folder does not exist")
    if not root.is_dir():
        raise SceneError(
            root, "is not a folder (a scene is a folder in one of the supported formats)"
        )
    for markers, name in MARKERS:
        if all((root / marker).is_file() for marker in markers):
            return name
    present = sorted(p.name for p in root.iterdir())[:10]
    expected = ", ".join(f"{' + '.join(m)} ({n})" for m, n in MARKERS)
    raise SceneError(
        root,
        f"unknown scene format: expected one of {expected}; found {present or 'an empty folder'}",
    )

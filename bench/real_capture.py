"""A real outdoor capture as a small nerfstudio scene: a rooftop cafe terrace in Giza, Egypt.

Source: the public GitHub repository Vincent7140/dataset_perso (snapshot commit
3db5ced2dc16cdd1d95f37f84958face30c7f347), files at its root:
  - transforms.json: nerfstudio (ns-process-data style) OpenGL camera-to-world poses of 302
    frames and one shared OPENCV camera (fl_x, fl_y, cx, cy, k1, k2, p1, p2) declared for
    1920x1080;
  - frame_00001.png .. frame_00302.png: frames of a handheld video walked round the terrace, stored
    at 480x270 (a quarter of the declared size), though transforms.json names them images/....
The scene shows the terrace (tables, chairs, lattice railings) with the Giza pyramids, the desert
and the town around it: an outward-looking, unbounded outdoor scene. The repository states no
licence (no LICENSE or README file): use it for local benchmarking only, do not redistribute it.

Fetch the repository with the `fetch` tool (github:Vincent7140/dataset_perso), then:
    python -m bench.real_capture --source /work/.mirror/Vincent7140+dataset_perso/repo \\
        --out scenes/giza-rooftop [--width 240]
The frames are resized to --width (aspect ratio kept), the intrinsics scaled to the written size,
and scenes/<name>/transforms.json + images/ written for model/scenes/formats/nerfstudio.py.
"""

from __future__ import annotations

import argparse
import io
import json
import shutil
import subprocess
from pathlib import Path, PurePosixPath

from PIL import Image, UnidentifiedImageError

REPOSITORY = "Vincent7140/dataset_perso"
SNAPSHOT = "3db5ced2dc16cdd1d95f37f84958face30c7f347"
CAMERA_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
DISTORTION_KEYS = ("k1", "k2", "p1", "p2")
DEFAULT_WIDTH = 240


def fail(message: str) -> SystemExit:
    return SystemExit(f"real_capture: {message}")


def git(source: Path, *args: str) -> bytes:
    """Output of one git command on the bare mirror; a failure names the command."""
    done = subprocess.run(
        ["git", "--git-dir", str(source), *args], capture_output=True, check=False
    )
    if done.returncode != 0:
        detail = done.stderr.decode(errors="replace").strip()
        raise fail(f"git {' '.join(args)} failed in {source}: {detail}")
    return done.stdout


def tree_files(source: Path) -> set[str]:
    """Paths of the files in the snapshot's newest commit."""
    if not source.is_dir():
        raise fail(f"{source} does not exist; fetch github:{REPOSITORY} first")
    listing = git(source, "ls-tree", "-r", "--name-only", "-z", "HEAD")
    return {p for p in listing.decode().split("\0") if p}


def read_transforms(source: Path, files: set[str]) -> dict:
    if "transforms.json" not in files:
        raise fail(f"{source} is not a snapshot of {REPOSITORY}: no transforms.json at its root")
    try:
        data = json.loads(git(source, "show", "HEAD:transforms.json"))
    except json.JSONDecodeError as exc:
        raise fail(f"transforms.json in {source} is not valid JSON ({exc})") from None
    missing = [k for k in (*CAMERA_KEYS, "frames") if k not in data]
    if missing:
        raise fail(f"transforms.json in {source} lacks {', '.join(missing)}: not {REPOSITORY}?")
    return data


def stored_name(file_path: str, files: set[str]) -> str:
    """The frame's path in the tree: transforms.json says images/<name>, the repository keeps the
    frames at its root."""
    name = PurePosixPath(file_path).name
    if name not in files:
        raise fail(f"frame {file_path!r} named in transforms.json is not in the snapshot")
    return name


def load_frame(source: Path, name: str) -> Image.Image:
    """One frame's pixels; a Git LFS pointer or a truncated blob is refused by name."""
    blob = git(source, "show", f"HEAD:{name}")
    if blob.startswith(b"version https://git-lfs"):
        raise fail(f"{name} is a Git LFS pointer, not an image; the snapshot lacks the pixels")
    try:
        image = Image.open(io.BytesIO(blob))
        image.load()
    except (UnidentifiedImageError, OSError) as exc:
        raise fail(f"{name} in {source} is not a readable image ({exc})") from None
    return image.convert("RGB")


def output_size(stored: tuple[int, int], width: int) -> tuple[int, int]:
    """The written size: `width` wide, aspect ratio kept; never larger than the stored frame (an
    upscale would add no detail, only pixels to train on)."""
    w, h = stored
    if not 1 <= width <= w:
        raise fail(f"--width must be 1 to {w} (the stored frames are {w}x{h}), got {width}")
    return width, max(1, round(h * width / w))


def camera(data: dict, size: tuple[int, int]) -> dict:
    """The shared camera at the written size. The intrinsics are declared for w x h (1920x1080),
    not for the stored frames, so they scale from the declared size. The distortion terms act on
    normalised coordinates and do not change."""
    sx, sy = size[0] / float(data["w"]), size[1] / float(data["h"])
    out = {
        "camera_model": "OPENCV",
        "fl_x": data["fl_x"] * sx,
        "fl_y": data["fl_y"] * sy,
        "cx": data["cx"] * sx,
        "cy": data["cy"] * sy,
        "w": size[0],
        "h": size[1],
    }
    out.update({k: float(data.get(k, 0.0)) for k in DISTORTION_KEYS})
    return out


def frame_list(data: dict, files: set[str]) -> list[tuple[str, list]]:
    """(stored name, pose) per frame in video order: the file lists them in reverse, and the loader
    holds out every 8th frame of the list, which should spread over the whole walk."""
    entries = data["frames"]
    if not isinstance(entries, list) or not all(
        isinstance(f, dict) and "file_path" in f and "transform_matrix" in f for f in entries
    ):
        raise fail("transforms.json 'frames' must list objects with file_path and transform_matrix")
    return sorted((stored_name(f["file_path"], files), f["transform_matrix"]) for f in entries)


def write_frames(source: Path, out: Path, frames: list, width: int) -> tuple[list, tuple]:
    """Resizes and writes every frame; returns the frame entries and the written size. The first
    frame fixes the size, checked before anything is written."""
    stored = load_frame(source, frames[0][0]).size
    size = output_size(stored, width)
    (out / "images").mkdir(parents=True, exist_ok=True)
    written = []
    for name, pose in frames:
        image = load_frame(source, name)
        if image.size != stored:
            # one shared camera in transforms.json: a frame of another size would not fit it
            raise fail(f"{name} is {image.size[0]}x{image.size[1]}, the first frame {stored}")
        image.resize(size, Image.Resampling.LANCZOS).save(out / "images" / name)
        # nerfstudio poses are already OpenGL camera-to-world, the loader's convention
        written.append({"file_path": f"images/{name}", "transform_matrix": pose})
    return written, size


def write_scene(source: Path, out: Path, width: int) -> int:
    """Builds the scene beside `out` and moves it into place whole: a failure half-way leaves
    `out` as it was."""
    files = tree_files(source)
    data = read_transforms(source, files)
    frames = frame_list(data, files)
    if not frames:
        raise fail(f"transforms.json in {source} lists no frames")
    partial = out.parent / f"{out.name}.partial"
    shutil.rmtree(partial, ignore_errors=True)
    try:
        written, size = write_frames(source, partial, frames, width)
        scene = {
            **camera(data, size),
            "frames": written,
            "source": {
                "repository": REPOSITORY,
                "commit": commit_of(source),
                "licence": "none stated",
            },
        }
        (partial / "transforms.json").write_text(json.dumps(scene, indent=2) + "\n")
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    shutil.rmtree(out, ignore_errors=True)
    partial.rename(out)
    return len(written)


def commit_of(source: Path) -> str:
    return git(source, "rev-parse", "HEAD").decode().strip()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", type=Path, required=True, help="the fetched bare git mirror")
    parser.add_argument("--out", type=Path, required=True, help="the scene folder to write")
    parser.add_argument("--width", type=int, default=DEFAULT_WIDTH, help="written image width")
    args = parser.parse_args(argv)
    count = write_scene(args.source, args.out, args.width)
    print(f"wrote {count} frames of {REPOSITORY} to {args.out}")
    if commit_of(args.source) != SNAPSHOT:
        # the frames or poses may have changed since the snapshot this script was written against
        print(f"note: the mirror's HEAD is not {SNAPSHOT}, the snapshot checked when writing this")


if __name__ == "__main__":
    main()

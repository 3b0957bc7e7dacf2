"""bench/real_capture.py rebuilds a capture from a fetched git snapshot: frames resized with their
intrinsics, video order, the loader reads the result; a wrong source is named and leaves nothing
behind."""

import json
import subprocess

import numpy as np
import pytest
from PIL import Image

from bench.real_capture import main as rebuild
from model.scenes import load_scene


def snapshot(root, frames=4, size=(48, 27), lfs=False):
    """A git repository laid out as the capture's: transforms.json declared at 4x the stored
    frames' size, frames at the root listed in reverse, as images/<name>."""
    root.mkdir()
    rng = np.random.default_rng(0)
    entries = []
    for i in range(frames, 0, -1):
        name = f"frame_{i:05d}.png"
        if lfs and i == 2:
            (root / name).write_text("version https://git-lfs.github.com/spec/v1\noid sha256:0\n")
        else:
            pixels = rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)
            Image.fromarray(pixels).save(root / name)
        angle = 0.4 * i
        pose = [
            [np.cos(angle), 0.0, np.sin(angle), 3 * np.sin(angle)],
            [0.0, 1.0, 0.0, 0.0],
            [-np.sin(angle), 0.0, np.cos(angle), 3 * np.cos(angle)],
            [0.0, 0.0, 0.0, 1.0],
        ]
        entries.append({"file_path": f"images/{name}", "transform_matrix": pose})
    w, h = 4 * size[0], 4 * size[1]
    camera = {"fl_x": 200.0, "fl_y": 200.0, "cx": w / 2, "cy": h / 2, "w": w, "h": h, "k1": 0.01}
    (root / "transforms.json").write_text(json.dumps({**camera, "frames": entries}))
    git = ["git", "-C", str(root), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run(git + ["init", "-q"], check=True)
    subprocess.run(git + ["add", "."], check=True)
    subprocess.run(git + ["commit", "-q", "-m", "capture"], check=True)
    return root / ".git"


def test_a_snapshot_becomes_a_scene_the_loader_reads(tmp_path):
    source = snapshot(tmp_path / "repo", frames=9)
    out = tmp_path / "scenes" / "capture"
    rebuild(["--source", str(source), "--out", str(out), "--width", "24"])
    written = json.loads((out / "transforms.json").read_text())
    assert (written["w"], written["h"]) == (24, 14)  # 27 * 24 / 48 = 13.5, rounded
    # declared for 192x108: the focal length scales by 24 / 192
    assert written["fl_x"] == pytest.approx(25.0) and written["k1"] == pytest.approx(0.01)
    names = [f["file_path"] for f in written["frames"]]
    assert names == [f"images/frame_{i:05d}.png" for i in range(1, 10)]  # video order
    with Image.open(out / names[0]) as image:
        assert image.size == (24, 14)
    scene = load_scene(out)
    assert sum(len(v.images) for v in scene.splits.values()) == 9


def test_a_wrong_source_is_named_and_leaves_the_old_scene(tmp_path):
    out = tmp_path / "capture"
    with pytest.raises(SystemExit, match="does not exist; fetch github:"):
        rebuild(["--source", str(tmp_path / "missing"), "--out", str(out)])
    good = snapshot(tmp_path / "good")
    rebuild(["--source", str(good), "--out", str(out), "--width", "24"])
    before = sorted(p.name for p in (out / "images").iterdir())
    broken = snapshot(tmp_path / "lfs", lfs=True)
    with pytest.raises(SystemExit, match="frame_00002.png is a Git LFS pointer"):
        rebuild(["--source", str(broken), "--out", str(out), "--width", "24"])
    assert sorted(p.name for p in (out / "images").iterdir()) == before
    assert not (tmp_path / "capture.partial").exists()
    with pytest.raises(SystemExit, match="--width must be 1 to 48"):
        rebuild(["--source", str(good), "--out", str(out), "--width", "96"])

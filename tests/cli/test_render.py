"""`leco render` and `leco export` on a run folder: a video along a generated path, the same path
rendered again from the camera path file it wrote (the dataset-frame round trip gives the same
frames), a nerfstudio camera_path.json, exports, and bad input named on stderr."""

import json

import numpy as np
import pytest
from PIL import Image

from cli.main import main
from workers.render.video import probe

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    from model.scenes.synthetic import generate
    from workers.config import TrainConfig
    from workers.train.run import run_training

    root = tmp_path_factory.mktemp("render-cli")
    generate("tiny", 0, root / "tiny-0")
    run_training(
        TrainConfig(method="leco", profile="smoke"), root / "tiny-0", root / "run", backend="local"
    )
    return root / "run"


def test_render_a_path_then_the_file_it_wrote(run_dir, tmp_path, capsys):
    first = tmp_path / "orbit.mp4"
    assert (
        main(
            [
                "render",
                "--run",
                str(run_dir),
                "--frames",
                "4",
                "--size",
                "64x48",
                "--fps",
                "8",
                "--out",
                str(first),
                "--depth-video",
            ]
        )
        == 0
    )
    summary = json.loads(capsys.readouterr().out)
    assert (
        summary["frames"] == 4 and summary["seconds_per_frame"] > 0 and summary["path"] == "orbit"
    )
    assert probe(first) == {
        "codec": "h264",
        "width": 64,
        "height": 48,
        "frames": 4,
        "fps": 8.0,
        "pix_fmt": "yuv420p",
    }
    assert probe(tmp_path / "orbit.depth.mp4")["frames"] == 4
    again = tmp_path / "again.mp4"
    assert (
        main(
            [
                "render",
                "--run",
                str(run_dir),
                "--path",
                str(tmp_path / "orbit.camera_path.json"),
                "--size",
                "64x48",
                "--out",
                str(again),
            ]
        )
        == 0
    )
    a = np.asarray(Image.open(tmp_path / "orbit.poster.png"), dtype=int)
    b = np.asarray(Image.open(tmp_path / "again.poster.png"), dtype=int)
    # the path through the dataset's frame and back renders the same picture
    assert np.abs(a - b).max() <= 2

    nerfstudio = {
        "camera_type": "perspective",
        "render_width": 64,
        "render_height": 48,
        "fps": 24,
        "camera_path": [
            {"camera_to_world": sum(c["c2w"], []) + [0, 0, 0, 1], "fov": 50, "aspect": 1.33}
            for c in json.loads((tmp_path / "orbit.camera_path.json").read_text())["cameras"]
        ],
    }
    (tmp_path / "camera_path.json").write_text(json.dumps(nerfstudio))
    assert (
        main(
            [
                "render",
                "--run",
                str(run_dir),
                "--path",
                str(tmp_path / "camera_path.json"),
                "--size",
                "64x48",
                "--out",
                str(tmp_path / "ns.mp4"),
            ]
        )
        == 0
    )
    assert probe(tmp_path / "ns.mp4")["frames"] == 4


def test_bad_render_input_is_named(run_dir, tmp_path, capsys):
    assert (
        main(["render", "--run", str(run_dir), "--path", "helix", "--out", str(tmp_path / "x.mp4")])
        == 2
    )
    assert "--path helix" in capsys.readouterr().err
    assert (
        main(["render", "--run", str(run_dir), "--size", "65x48", "--out", str(tmp_path / "x.mp4")])
        == 2
    )
    assert "width" in capsys.readouterr().err
    (tmp_path / "bad.json").write_text(json.dumps([[[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]]))
    assert (
        main(
            [
                "render",
                "--run",
                str(run_dir),
                "--path",
                str(tmp_path / "bad.json"),
                "--out",
                str(tmp_path / "x.mp4"),
            ]
        )
        == 2
    )
    # the union tag (kind) is in the path
    assert "path.cameras.cameras.0.c2w" in capsys.readouterr().err
    assert not list(tmp_path.glob("x*.mp4"))


def test_exports_write_their_file_and_the_transform(run_dir, tmp_path, capsys):
    for what, name in (
        ("cameras", "cameras.json"),
        ("occupancy", "occupancy.ply"),
        ("pointcloud", "pointcloud.ply"),
    ):
        out = tmp_path / what
        assert (
            main(
                [
                    "export",
                    what,
                    "--run",
                    str(run_dir),
                    "--out",
                    str(out),
                    "--stride",
                    "4",
                    "--min-opacity",
                    "0",
                    "--resolution",
                    "16",
                ]
            )
            == 0
        )
        info = json.loads(capsys.readouterr().out)
        assert (
            info["file"] == name and (out / name).is_file() and (out / "transform.json").is_file()
        )
    cameras = json.loads((tmp_path / "cameras" / "cameras.json").read_text())
    assert cameras["units"] == "metres" and len(cameras["cameras"]) == 12

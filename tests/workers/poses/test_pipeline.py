"""The pipeline on a synthetic drone flight with exact cameras: pycolmap's poses against the truth,
the GPS frame in metres, resume, cancel, limits and the inputs it refuses."""

import json
import shutil

import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")

from bench.photo_flight import pose_errors  # noqa: E402
from model.errors import Failed, InvalidInput  # noqa: E402
from model.scenes import load_scene  # noqa: E402
from workers.poses.exif import write_jpeg  # noqa: E402
from workers.poses.pipeline import find_poses, work_folder  # noqa: E402
from workers.poses.process import PosesCancelled, run_poses  # noqa: E402
from workers.poses.settings import PosesConfig  # noqa: E402

pytestmark = pytest.mark.slow
CONFIG = PosesConfig(max_image_size=320)


class Events(list):
    def __call__(self, event: dict) -> None:
        self.append(event)

    def messages(self) -> str:
        return "\n".join(e.get("message", "") for e in self)


@pytest.fixture(scope="module")
def posed(flight, tmp_path_factory):
    out = tmp_path_factory.mktemp("posed") / "scene"
    events = Events()
    summary = run_poses(flight / "photos", out, CONFIG, events)
    return out, summary, events


def truth_of(flight) -> dict:
    return json.loads((flight / "truth.json").read_text())


def test_poses_match_the_exact_cameras_and_gps_gives_metres(flight, posed):
    out, summary, events = posed
    errors = pose_errors(truth_of(flight), out)
    assert errors["registered"] == errors["photos"] == summary["registered"]
    assert errors["centre_error_share"]["max"] < 0.01  # of the extent
    assert errors["rotation_error_deg"]["max"] < 1.0
    assert errors["scale"] == pytest.approx(1.0, abs=0.01)  # the scene is in true metres
    assert errors["frame_rotation_deg"] < 1.0  # and east-north-up: gravity along +z
    geo = summary["georeference"]
    assert geo["photos_with_gps"] == errors["photos"] and geo["gps_error_m"]["max"] < 1.0
    assert summary["matcher"]["name"] == "spatial"
    assert "matcher: spatial" in events.messages()


def test_every_stage_reports_progress_to_its_end(posed):
    _, _, events = posed
    stages = [e["stage"] for e in events if e["event"] == "stage"]
    assert stages == ["features", "matching", "mapping", "alignment", "export"]
    last = {}
    for e in events:
        if e["event"] == "progress":
            assert 0 <= e["done"] <= e["total"]
            last[e["stage"]] = e
    assert last["features"]["done"] == last["features"]["total"]
    assert last["matching"]["done"] == last["matching"]["total"]


def test_the_posed_folder_is_a_scene_in_metres(posed):
    out, summary, _ = posed
    scene = load_scene(out)
    assert scene.format == "colmap" and scene.normalization.units == "metres"
    assert sum(len(s.names) for s in scene.splits.values()) == summary["registered"]
    assert scene.extras["georeference"]["frame"] == "ENU"
    assert json.loads((out / "poses.json").read_text())["registered"] == summary["registered"]
    assert not work_folder(out).exists()


def test_photos_without_exif_share_one_camera_and_keep_their_own_frame(flight, tmp_path):
    """The flight's photos saved again without EXIF (as frames cut from a video are): no GPS, no
    focal length (COLMAP's default, said in a warning), one shared camera. Numbered names without
    camera EXIF read as a video: auto picks sequential pairs (here every pair is asked for)."""
    from PIL import Image

    bare = tmp_path / "bare"
    bare.mkdir()
    for photo in sorted((flight / "photos").iterdir()):
        with Image.open(photo) as image:
            image.convert("RGB").save(bare / photo.name, quality=95)
    out, events = tmp_path / "scene", Events()
    summary = find_poses(bare, out, CONFIG.model_copy(update={"matcher": "exhaustive"}), events)
    errors = pose_errors(truth_of(flight), out)
    assert summary["georeference"] is None and summary["matcher"]["name"] == "exhaustive"
    assert summary["cameras"] == 1 and summary["registered"] == 30
    assert "no usable EXIF focal length" in " ".join(summary["warnings"])
    assert errors["centre_error_share"]["max"] < 0.01
    assert errors["rotation_error_deg"]["max"] < 1.0
    assert not (out / "georeference.json").exists()
    assert load_scene(out).normalization.units == "source units"


class Stop(Exception):
    pass


def test_a_run_stopped_after_features_resumes_from_them(flight, tmp_path):
    out = tmp_path / "scene"

    def stop_at_matching(event):
        if event.get("stage") == "matching":
            raise Stop

    with pytest.raises(Stop):
        find_poses(flight / "photos", out, CONFIG, stop_at_matching)
    assert not out.exists()  # nothing half-written
    state = json.loads((work_folder(out) / "state.json").read_text())
    assert state["done"] == ["features"]
    events = Events()
    summary = find_poses(flight / "photos", out, CONFIG, events)
    assert "resuming after features" in events.messages()
    assert summary["registered"] == 30 and "features" in summary["seconds"]


def test_a_cancel_stops_the_process_and_keeps_the_finished_stages(flight, tmp_path):
    out = tmp_path / "scene"
    seen = []

    def record(event):
        seen.append(event)

    with pytest.raises(PosesCancelled, match="cancelled during matching"):
        run_poses(
            flight / "photos",
            out,
            CONFIG,
            record,
            cancelled=lambda: any(e.get("stage") == "matching" for e in seen),
        )
    assert not out.exists()
    assert "features" in json.loads((work_folder(out) / "state.json").read_text())["done"]


def test_the_time_limit_stops_the_run_saying_so(flight, tmp_path):
    with pytest.raises(Failed, match="time_limit_s=0.5"):
        run_poses(
            flight / "photos",
            tmp_path / "scene",
            CONFIG.model_copy(update={"time_limit_s": 0.5}),
            Events(),
        )


def test_photos_that_share_nothing_are_refused_saying_how_many_registered(tmp_path):
    folder = tmp_path / "noise"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(6):
        noise = (rng.random((120, 160, 3)) * 255).astype(np.uint8)
        write_jpeg(folder / f"IMG_{i}.JPG", noise, focal_px=150.0)
    with pytest.raises(InvalidInput, match="no model could be built|registered") as info:
        run_poses(folder, tmp_path / "scene", CONFIG, Events())
    assert "overlap" in str(info.value)
    assert not (tmp_path / "scene").exists()


def test_a_model_under_the_registered_share_is_refused(flight, tmp_path):
    """The flight's last row (7 photos) replaced by noise of the same size: the rest register."""
    folder = tmp_path / "mixed"
    shutil.copytree(flight / "photos", folder)
    rng = np.random.default_rng(1)
    for path in sorted(folder.iterdir())[-7:]:
        noise = (rng.random((240, 320, 3)) * 255).astype(np.uint8)
        write_jpeg(path, noise, focal_px=200.0)
    config = CONFIG.model_copy(update={"min_registered": 0.9})
    with pytest.raises(InvalidInput, match=r"only \d+ of 30 photos \(\d+%\) registered") as info:
        run_poses(folder, tmp_path / "scene", config, Events())
    assert "min_registered 90%" in str(info.value)
    assert not (tmp_path / "scene").exists()


def test_an_output_that_holds_files_is_refused_before_anything_runs(flight, tmp_path):
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "keep.txt").write_text("mine")
    with pytest.raises(InvalidInput, match="must not exist or be an empty folder"):
        run_poses(flight / "photos", tmp_path / "scene", CONFIG, Events())
    assert (tmp_path / "scene" / "keep.txt").read_text() == "mine"


def test_a_memory_limit_too_small_fails_saying_so(flight, tmp_path):
    with pytest.raises(Failed, match="memory_limit_mb=256"):
        run_poses(
            flight / "photos",
            tmp_path / "scene",
            CONFIG.model_copy(update={"memory_limit_mb": 256}),
            Events(),
        )
    assert not (tmp_path / "scene").exists()

from pathlib import Path

import numpy as np
import pytest

from workers.poses.exif import PhotoExif
from workers.poses.pairs import exhaustive, plan, sequential, spatial, video_frames
from workers.poses.photos import Photo, Photos
from workers.poses.settings import PosesConfig

CAMERA = PhotoExif(800.0, "FocalLength and FocalPlaneXResolution", None, "DJI FC7303", "")
NOTHING = PhotoExif(None, "no focal length in EXIF", None, "", "")


def photos(names: list[str], exif: PhotoExif = CAMERA) -> Photos:
    return Photos(Path("."), [Photo(n, Path(n), 640, 480, exif) for n in names], [])


def test_exhaustive_is_every_pair_once():
    pairs = exhaustive(7)
    assert len(pairs) == 21 == len(set(pairs)) and all(i < j for i, j in pairs)


def test_sequential_takes_the_next_photos_and_powers_of_two():
    pairs = set(sequential(40, 3))
    assert {(0, 1), (0, 2), (0, 3), (0, 4), (10, 13), (10, 14)} <= pairs
    assert (0, 5) not in pairs and (10, 15) not in pairs
    assert all(j < 40 for _, j in pairs)
    assert len(sequential(2, 10)) == 1


def test_spatial_takes_the_nearest_on_the_ground():
    # a line of photos 10 m apart; altitude differences do not count
    positions = np.array([[10.0 * i, 0.0, 100.0 * (i % 2)] for i in range(10)])
    pairs = set(spatial(positions, 2))
    assert {(0, 1), (0, 2), (3, 4), (4, 5)} <= pairs  # 1 is nearest to 0 though 100 m higher
    assert (0, 3) not in pairs
    assert len(spatial(positions, 50)) == 45  # more neighbours than photos: every pair


def test_numbered_frames_without_camera_exif_are_a_video():
    frames = [f"frame_{i:05d}.png" for i in range(1, 30)]
    assert video_frames(photos(frames, NOTHING))
    assert not video_frames(photos(frames, CAMERA))  # a camera's numbered photos
    assert not video_frames(photos(["a.png", "b.png", "c.png"], NOTHING))


def test_auto_picks_by_what_the_photos_carry():
    config = PosesConfig(exhaustive_max=20)
    few = photos([f"IMG_{i}.JPG" for i in range(12)])
    gps = np.zeros((12, 3))
    gps[:, 0] = np.arange(12)
    assert plan(few, config, gps).matcher == "spatial"
    assert plan(few, config, None).matcher == "exhaustive"
    many = photos([f"IMG_{i:03d}.JPG" for i in range(30)])
    chosen = plan(many, config, None)
    assert chosen.matcher == "sequential" and "more than 20" in chosen.reason
    video = photos([f"frame_{i:05d}.png" for i in range(12)], NOTHING)
    assert plan(video, config, None).matcher == "sequential"
    assert plan(video, config.model_copy(update={"matcher": "exhaustive"}), None).pairs == (
        exhaustive(12)
    )


def test_spatial_without_gps_on_every_photo_is_refused_saying_how_many_have_it():
    with pytest.raises(ValueError, match="0 of 6 carry it"):
        plan(photos([f"{i}.jpg" for i in range(6)]), PosesConfig(matcher="spatial"), None)

import numpy as np
import pytest

from model.scenes.errors import SceneError
from workers.poses.exif import write_jpeg
from workers.poses.photos import scan
from workers.poses.settings import PosesConfig

CONFIG = PosesConfig(min_photos=3)


def rgb(width: int = 40, height: int = 30, seed: int = 0) -> np.ndarray:
    return (np.random.default_rng(seed).random((height, width, 3)) * 255).astype(np.uint8)


def folder_of(tmp_path, n: int, **kw):
    folder = tmp_path / "photos"
    folder.mkdir()
    for i in range(n):
        write_jpeg(folder / f"IMG_{i}.JPG", rgb(seed=i), **{"focal_px": 30.0, **kw})
    return folder


def test_photos_are_described(tmp_path):
    folder = folder_of(tmp_path, 4, gps=(47.0, 8.0, 400.0))
    (folder / "notes.txt").write_text("flight log")
    write_jpeg(folder / "IMG_9.JPG", rgb(80, 60), focal_px=None)
    photos = scan(folder, CONFIG)
    assert photos.names == [f"IMG_{i}.JPG" for i in (0, 1, 2, 3, 9)]
    assert photos.summary() == {
        "photos": 5,
        "sizes": {"40x30": 4, "80x60": 1},
        "cameras": 2,
        "with_gps": 4,
        "with_focal": 4,
        "skipped": 1,
    }
    warnings = " ".join(photos.warnings())
    assert "1 of 5 photos have no usable EXIF focal length (IMG_9.JPG" in warnings
    assert "1.2 x the longer side" in warnings
    assert "only 4 of 5 photos carry EXIF GPS" in warnings
    assert "1 files are not photos" in warnings and "notes.txt" in warnings


def test_too_few_photos_are_refused_saying_how_many(tmp_path):
    folder = folder_of(tmp_path, 2)
    with pytest.raises(SceneError, match="holds 2 photos .* at least 3"):
        scan(folder, CONFIG)


def test_a_truncated_photo_is_named(tmp_path):
    folder = folder_of(tmp_path, 4)
    whole = (folder / "IMG_2.JPG").read_bytes()
    (folder / "IMG_2.JPG").write_bytes(whole[: len(whole) // 2])
    with pytest.raises(SceneError, match="truncated or damaged") as info:
        scan(folder, CONFIG)
    assert info.value.path == folder / "IMG_2.JPG"


def test_a_file_that_is_no_image_is_named(tmp_path):
    folder = folder_of(tmp_path, 4)
    (folder / "IMG_7.jpg").write_bytes(b"not a jpeg at all")
    with pytest.raises(SceneError, match="not an image") as info:
        scan(folder, CONFIG)
    assert info.value.path.name == "IMG_7.jpg"


def test_a_missing_folder_is_named(tmp_path):
    with pytest.raises(SceneError, match="not a folder of photos"):
        scan(tmp_path / "nowhere", CONFIG)

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from workers.poses.exif import (
    EXIF_IFD,
    FOCAL_35MM,
    FOCAL_LENGTH,
    read_exif,
    write_jpeg,
)

RGB = (np.random.default_rng(0).random((30, 40, 3)) * 255).astype(np.uint8)


def exif_of(path: Path):
    with Image.open(path) as image:
        return read_exif(image)


@pytest.mark.parametrize(
    "gps", [(47.3769123, 8.5417456, 408.25), (-33.8567844, -151.2152967, -12.5)]
)
def test_focal_and_gps_read_back_as_written(tmp_path, gps):
    write_jpeg(tmp_path / "a.jpg", RGB, focal_px=31.4159, gps=gps)
    exif = exif_of(tmp_path / "a.jpg")
    assert exif.focal_px == pytest.approx(31.4159, rel=1e-6)
    assert exif.focal_source == "FocalLength and FocalPlaneXResolution"
    assert exif.gps[0] == pytest.approx(gps[0], abs=1e-8)  # about a millimetre
    assert exif.gps[1] == pytest.approx(gps[1], abs=1e-8)
    assert exif.gps[2] == pytest.approx(gps[2], abs=1e-3)
    assert exif.camera == "LeCO synthetic flight"


def test_a_photo_resized_after_it_was_taken_scales_its_focal(tmp_path):
    """PixelXDimension says the width the sensor's pixels per mm refer to."""
    big = np.repeat(np.repeat(RGB, 2, axis=0), 2, axis=1)
    write_jpeg(tmp_path / "big.jpg", big, focal_px=80.0)
    with Image.open(tmp_path / "big.jpg") as image:
        exif = image.getexif()
        image.resize((40, 30)).save(tmp_path / "small.jpg", exif=exif)
    assert exif_of(tmp_path / "small.jpg").focal_px == pytest.approx(40.0, rel=1e-6)


def test_the_35mm_equivalent_is_used_without_a_sensor_size(tmp_path):
    exif = Image.Exif()
    tags = exif.get_ifd(EXIF_IFD)
    tags[FOCAL_LENGTH] = 4.25
    tags[FOCAL_35MM] = 27
    Image.fromarray(RGB).save(tmp_path / "phone.jpg", exif=exif)
    got = exif_of(tmp_path / "phone.jpg")
    assert got.focal_px == pytest.approx(27 / 36 * 40)
    assert got.focal_source == "FocalLengthIn35mmFilm"


def test_no_exif_says_so(tmp_path):
    Image.fromarray(RGB).save(tmp_path / "plain.png")
    got = exif_of(tmp_path / "plain.png")
    assert got.focal_px is None and got.gps is None and got.camera == ""
    assert got.focal_source == "no focal length in EXIF"

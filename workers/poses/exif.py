"""The EXIF a photo's pose starts from: its focal length in pixels and its GPS position. Read with
Pillow, so the pipeline says what it found before COLMAP runs; `write_jpeg` writes the same tags
(the synthetic photo flight and the tests)."""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image
from PIL.TiffImagePlugin import IFDRational

EXIF_IFD = 0x8769
GPS_IFD = 0x8825
MAKE, MODEL = 0x010F, 0x0110
DATETIME_ORIGINAL = 0x9003
FOCAL_LENGTH = 0x920A  # millimetres
FOCAL_35MM = 0xA405  # the same lens's focal length on 35 mm film (36 x 24 mm)
PIXEL_X_DIMENSION = 0xA002
PIXEL_Y_DIMENSION = 0xA003
FOCAL_PLANE_X_RESOLUTION = 0xA20E  # sensor pixels per FOCAL_PLANE_UNIT
FOCAL_PLANE_UNIT = 0xA210
MM_PER_UNIT = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # inch, centimetre, (and the extensions) mm, um
FILM_WIDTH_MM = 36.0
LAT_REF, LAT, LON_REF, LON, ALT_REF, ALT = 1, 2, 3, 4, 5, 6


@dataclass(frozen=True)
class PhotoExif:
    focal_px: float | None  # focal length in pixels of the photo as stored
    focal_source: str  # which tags gave it, or why there is none
    gps: tuple[float, float, float] | None  # latitude, longitude (degrees), altitude (m)
    camera: str  # make and model, "" when unknown
    timestamp: str  # DateTimeOriginal, "" when unknown


def _number(value: Any) -> float | None:
    try:
        number = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return number if np.isfinite(number) else None


def _focal(exif: dict, width: int, height: int) -> tuple[float | None, str]:
    focal_mm = _number(exif.get(FOCAL_LENGTH))
    per_unit = _number(exif.get(FOCAL_PLANE_X_RESOLUTION))
    unit = MM_PER_UNIT.get(int(exif.get(FOCAL_PLANE_UNIT, 2) or 2))
    if focal_mm and focal_mm > 0 and per_unit and per_unit > 0 and unit:
        focal = focal_mm * per_unit / unit
        stored_width = _number(exif.get(PIXEL_X_DIMENSION))
        if stored_width and stored_width > 0:  # the photo was resized after it was taken
            focal *= width / stored_width
        return focal, "FocalLength and FocalPlaneXResolution"
    focal_35 = _number(exif.get(FOCAL_35MM))
    if focal_35 and focal_35 > 0:
        return focal_35 / FILM_WIDTH_MM * max(width, height), "FocalLengthIn35mmFilm"
    if focal_mm:
        return None, "FocalLength without a sensor size"
    return None, "no focal length in EXIF"


def _degrees(value: Any, ref: object) -> float | None:
    try:
        d, m, s = (float(Fraction(v.numerator, v.denominator)) for v in value)
    except (TypeError, ValueError, ZeroDivisionError, AttributeError):
        try:
            d, m, s = (float(v) for v in value)
        except (TypeError, ValueError, ZeroDivisionError):
            return None
    angle = d + m / 60 + s / 3600
    return -angle if str(ref).upper().startswith(("S", "W")) else angle


def _gps(gps: dict) -> tuple[float, float, float] | None:
    if LAT not in gps or LON not in gps:
        return None
    lat = _degrees(gps[LAT], gps.get(LAT_REF, "N"))
    lon = _degrees(gps[LON], gps.get(LON_REF, "E"))
    if lat is None or lon is None or not (-90 <= lat <= 90 and -180 <= lon <= 180):
        return None
    alt = _number(gps.get(ALT)) or 0.0
    below = gps.get(ALT_REF, 0)
    if below in (1, b"\x01"):
        alt = -alt
    return lat, lon, alt


def read_exif(image: Image.Image) -> PhotoExif:
    """What an opened photo's EXIF says about its camera and position."""
    exif = image.getexif()
    tags = {**dict(exif), **dict(exif.get_ifd(EXIF_IFD))}
    focal, source = _focal(tags, *image.size)
    camera = " ".join(str(tags.get(t, "")).strip("\x00 ") for t in (MAKE, MODEL)).strip()
    return PhotoExif(
        focal_px=focal,
        focal_source=source,
        gps=_gps(dict(exif.get_ifd(GPS_IFD))),
        camera=camera,
        timestamp=str(tags.get(DATETIME_ORIGINAL, "")).strip("\x00 "),
    )


def _rational(value: float, denominator: int = 1_000_000) -> IFDRational:
    return IFDRational(int(round(abs(value) * denominator)), denominator)


def _dms(angle: float) -> tuple[IFDRational, IFDRational, IFDRational]:
    angle = abs(angle)
    d = int(angle)
    m = int((angle - d) * 60)
    s = (angle - d - m / 60) * 3600
    return IFDRational(d, 1), IFDRational(m, 1), _rational(s)


def write_jpeg(
    path: Path,
    rgb: np.ndarray,
    *,
    focal_px: float | None,
    gps: tuple[float, float, float] | None = None,
    camera: tuple[str, str] = ("LeCO", "synthetic flight"),
    quality: int = 95,
) -> None:
    """A JPEG with the EXIF a camera writes: make and model, the focal length in millimetres with
    the sensor's pixels per millimetre (so focal_px is exact), and the GPS position."""
    height, width = rgb.shape[:2]
    exif = Image.Exif()
    exif[MAKE], exif[MODEL] = camera
    tags = exif.get_ifd(EXIF_IFD)
    tags[DATETIME_ORIGINAL] = "2026:01:01 12:00:00"
    tags[PIXEL_X_DIMENSION], tags[PIXEL_Y_DIMENSION] = width, height
    if focal_px is not None:
        pixels_per_mm = width / 6.4  # a 6.4 mm wide sensor, as a phone's or a small drone's
        tags[FOCAL_LENGTH] = _rational(focal_px / pixels_per_mm)
        tags[FOCAL_PLANE_X_RESOLUTION] = _rational(pixels_per_mm)
        tags[FOCAL_PLANE_UNIT] = 4
    if gps is not None:
        lat, lon, alt = gps
        place = exif.get_ifd(GPS_IFD)
        place[LAT_REF], place[LAT] = ("N" if lat >= 0 else "S"), _dms(lat)
        place[LON_REF], place[LON] = ("E" if lon >= 0 else "W"), _dms(lon)
        place[ALT_REF], place[ALT] = (0 if alt >= 0 else 1), _rational(alt, 10_000)
    Image.fromarray(rgb).save(path, format="JPEG", quality=quality, exif=exif)

"""WGS84 latitude, longitude and altitude to local east-north-up metres and back (through
Earth-centred, Earth-fixed coordinates): GPS positions of photos become a metric frame with gravity
along +z, as the synthetic city's is."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

A = 6378137.0  # WGS84 semi-major axis, metres
F = 1 / 298.257223563  # WGS84 flattening
E2 = F * (2 - F)  # first eccentricity squared


@dataclass(frozen=True)
class Geodetic:
    latitude: float  # degrees, north positive
    longitude: float  # degrees, east positive
    altitude: float  # metres above the ellipsoid (EXIF says above sea level: the offset is shared)


def to_ecef(points: np.ndarray) -> np.ndarray:
    """(N, 3) latitude, longitude (degrees), altitude (m) -> (N, 3) ECEF metres."""
    lat, lon = np.radians(points[:, 0]), np.radians(points[:, 1])
    h = points[:, 2]
    n = A / np.sqrt(1 - E2 * np.sin(lat) ** 2)  # prime vertical radius of curvature
    return np.stack(
        [
            (n + h) * np.cos(lat) * np.cos(lon),
            (n + h) * np.cos(lat) * np.sin(lon),
            (n * (1 - E2) + h) * np.sin(lat),
        ],
        axis=1,
    )


def from_ecef(xyz: np.ndarray) -> np.ndarray:
    """(N, 3) ECEF metres -> latitude, longitude (degrees), altitude (m); Bowring's start and three
    fixed-point steps, below a micrometre anywhere near the Earth's surface."""
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    lat = np.arctan2(z, p * (1 - E2))
    for _ in range(5):
        n = A / np.sqrt(1 - E2 * np.sin(lat) ** 2)
        h = p / np.cos(lat) - n
        lat = np.arctan2(z, p * (1 - E2 * n / (n + h)))
    n = A / np.sqrt(1 - E2 * np.sin(lat) ** 2)
    h = p / np.cos(lat) - n
    return np.stack([np.degrees(lat), np.degrees(lon), h], axis=1)


def enu_rotation(origin: Geodetic) -> np.ndarray:
    """(3, 3) rows east, north, up at the origin, in ECEF axes."""
    lat, lon = math.radians(origin.latitude), math.radians(origin.longitude)
    return np.array(
        [
            [-math.sin(lon), math.cos(lon), 0.0],
            [-math.sin(lat) * math.cos(lon), -math.sin(lat) * math.sin(lon), math.cos(lat)],
            [math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)],
        ]
    )


def _origin_ecef(origin: Geodetic) -> np.ndarray:
    return to_ecef(np.array([[origin.latitude, origin.longitude, origin.altitude]]))[0]


def to_enu(points: np.ndarray, origin: Geodetic) -> np.ndarray:
    """(N, 3) latitude, longitude, altitude -> (N, 3) metres east, north, up of `origin`."""
    return (to_ecef(points) - _origin_ecef(origin)) @ enu_rotation(origin).T


def from_enu(enu: np.ndarray, origin: Geodetic) -> np.ndarray:
    """(N, 3) metres east, north, up of `origin` -> latitude, longitude, altitude."""
    return from_ecef(enu @ enu_rotation(origin) + _origin_ecef(origin))


def centre(points: np.ndarray) -> Geodetic:
    """The origin of a capture's local frame: the mean of its GPS positions (taken in ECEF, so it
    is right across the antimeridian too)."""
    lat, lon, _ = from_ecef(to_ecef(points).mean(axis=0, keepdims=True))[0]
    # the mean ECEF point lies below the surface: keep the mean altitude instead
    return Geodetic(float(lat), float(lon), float(points[:, 2].mean()))

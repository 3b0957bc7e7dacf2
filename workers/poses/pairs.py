"""Which photos are matched with which: the matcher picked from the photos (and said why), and its
image pairs, listed here so that matching runs in chunks that report progress and resume."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from workers.poses.photos import Photos
from workers.poses.settings import PosesConfig

FRAME_NUMBER = re.compile(r"^(.*?)(\d+)$")


@dataclass(frozen=True)
class MatchPlan:
    matcher: str  # exhaustive | sequential | spatial
    reason: str  # why, for the log
    pairs: list[tuple[int, int]]  # indices into the photos, i < j


def video_frames(photos: Photos) -> bool:
    """Frames cut from a video: no camera EXIF at all, and names that count up in one run
    (frame_00001.png, frame_00002.png, ...)."""
    if any(p.exif.camera or p.exif.focal_px for p in photos.photos):
        return False
    numbers = []
    prefixes = set()
    for photo in photos.photos:
        match = FRAME_NUMBER.match(photo.name.rsplit(".", 1)[0])
        if not match:
            return False
        prefixes.add(match.group(1))
        numbers.append(int(match.group(2)))
    steps = np.diff(sorted(numbers))
    return len(prefixes) == 1 and len(steps) > 0 and bool((steps > 0).all()) and steps.max() <= 3


def exhaustive(n: int) -> list[tuple[int, int]]:
    return [(i, j) for i in range(n) for j in range(i + 1, n)]


def sequential(n: int, overlap: int) -> list[tuple[int, int]]:
    """Each photo with the `overlap` after it, and (COLMAP's quadratic overlap) with those 2^k
    after it for k < overlap, which closes loops over longer gaps."""
    pairs = set()
    for i in range(n):
        for j in range(i + 1, min(n, i + overlap + 1)):
            pairs.add((i, j))
        for k in range(overlap):
            if i + 2**k < n:
                pairs.add((i, i + 2**k))
            else:
                break
    return sorted(pairs)


def spatial(positions: np.ndarray, neighbours: int) -> list[tuple[int, int]]:
    """Each photo with its `neighbours` nearest by GPS, measured on the ground (altitude from GPS
    is the least accurate coordinate, as COLMAP's spatial matcher also assumes)."""
    flat = positions[:, :2]
    distances = np.linalg.norm(flat[:, None] - flat[None], axis=-1)
    np.fill_diagonal(distances, np.inf)
    k = min(neighbours, len(positions) - 1)
    nearest = np.argsort(distances, axis=1, kind="stable")[:, :k]
    pairs = {(min(i, int(j)), max(i, int(j))) for i in range(len(positions)) for j in nearest[i]}
    return sorted(pairs)


def plan(photos: Photos, config: PosesConfig, positions: np.ndarray | None) -> MatchPlan:
    """The matcher and its pairs. `positions`: each photo's GPS in local metres, or None when not
    every photo has one."""
    n = len(photos)
    choice = config.matcher
    if choice == "auto":
        if positions is not None:
            choice = "spatial"
            reason = f"every photo carries GPS: each with its {config.spatial_neighbors} nearest"
        elif video_frames(photos):
            choice, reason = "sequential", "numbered frames without camera EXIF: a video"
        elif n <= config.exhaustive_max:
            choice = "exhaustive"
            reason = f"{n} photos, at most {config.exhaustive_max}: every pair"
        else:
            choice = "sequential"
            reason = (
                f"{n} photos, more than {config.exhaustive_max}, without GPS: in name order (set "
                "matcher=exhaustive if the names do not follow the flight)"
            )
    else:
        reason = "as asked"
    if choice == "spatial":
        if positions is None:
            raise ValueError(
                "matcher=spatial needs EXIF GPS on every photo; "
                f"{len(photos.with_gps)} of {n} carry it"
            )
        pairs = spatial(positions, config.spatial_neighbors)
    elif choice == "sequential":
        pairs = sequential(n, config.sequential_overlap)
    else:
        pairs = exhaustive(n)
    return MatchPlan(choice, reason, pairs)

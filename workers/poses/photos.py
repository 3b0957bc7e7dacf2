"""A folder of photos checked before any pose is sought: every photo decodes whole (a truncated or
damaged one is named), their sizes and cameras are counted, and what EXIF says of each (focal
length, GPS) is read. Whatever is wrong is said before COLMAP starts."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from PIL import Image, UnidentifiedImageError

from model.scenes.errors import SceneError
from model.scenes.limits import MAX_PIXELS
from workers.poses.exif import PhotoExif, read_exif
from workers.poses.settings import PHOTO_SUFFIXES, PosesConfig

MAX_PHOTOS = 20_000  # COLMAP's exhaustive matching is quadratic; beyond this nobody poses at once
DEFAULT_FOCAL_FACTOR = 1.2  # COLMAP's default focal length, times the longer side, without EXIF


@dataclass(frozen=True)
class Photo:
    name: str  # relative to the folder, with / (COLMAP's image name)
    path: Path
    width: int
    height: int
    exif: PhotoExif

    @property
    def size(self) -> str:
        return f"{self.width}x{self.height}"


@dataclass(frozen=True)
class Photos:
    folder: Path
    photos: list[Photo]
    skipped: list[str]  # files that are not photos (by suffix), left out

    def __len__(self) -> int:
        return len(self.photos)

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.photos]

    @property
    def with_gps(self) -> list[Photo]:
        return [p for p in self.photos if p.exif.gps is not None]

    def warnings(self) -> list[str]:
        """What the run goes on without, said once each."""
        out = []
        missing = [p for p in self.photos if p.exif.focal_px is None]
        if missing:
            out.append(
                f"{len(missing)} of {len(self)} photos have no usable EXIF focal length "
                f"({missing[0].name}: {missing[0].exif.focal_source}); their cameras start from "
                f"COLMAP's default, {DEFAULT_FOCAL_FACTOR} x the longer side in pixels, and "
                "bundle adjustment refines it"
            )
        gps = len(self.with_gps)
        if 0 < gps < len(self):
            out.append(f"only {gps} of {len(self)} photos carry EXIF GPS")
        if self.skipped:
            out.append(
                f"{len(self.skipped)} files are not photos and are left out ({self.skipped[0]}; "
                f"photos end in {', '.join(PHOTO_SUFFIXES)})"
            )
        return out

    def summary(self) -> dict:
        sizes = Counter(p.size for p in self.photos)
        cameras = Counter((p.exif.camera, p.size) for p in self.photos)
        return {
            "photos": len(self),
            "sizes": dict(sizes),
            "cameras": len(cameras),
            "with_gps": len(self.with_gps),
            "with_focal": sum(p.exif.focal_px is not None for p in self.photos),
            "skipped": len(self.skipped),
        }


def _is_photo(path: Path) -> bool:
    return path.suffix.lower() in PHOTO_SUFFIXES


def _read(path: Path, name: str) -> Photo:
    try:
        with Image.open(path) as image:
            width, height = image.size
            if width * height > MAX_PIXELS:
                raise SceneError(
                    path,
                    f"photo claims {width}x{height} pixels, more than the "
                    f"{MAX_PIXELS // 10**6} megapixel limit",
                )
            exif = read_exif(image)
            image.load()  # decodes every pixel: a photo cut short fails here, not in COLMAP
    except SceneError:
        raise
    except Image.DecompressionBombError as exc:
        raise SceneError(path, f"photo claims too many pixels: {exc}") from None
    except UnidentifiedImageError:
        raise SceneError(path, "not an image Pillow can read (renamed or damaged?)") from None
    except (OSError, SyntaxError, ValueError) as exc:
        raise SceneError(path, f"photo is truncated or damaged: {exc}") from None
    return Photo(name, path, width, height, exif)


def scan(folder: Path, config: PosesConfig) -> Photos:
    """Every photo of `folder` (and its subfolders), in name order, checked and described."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SceneError(folder, "not a folder of photos")
    files = sorted(p for p in folder.rglob("*") if p.is_file() and not p.name.startswith("."))
    names = [p.relative_to(folder).as_posix() for p in files]
    skipped = [n for p, n in zip(files, names) if not _is_photo(p)]
    chosen = [(p, n) for p, n in zip(files, names) if _is_photo(p)]
    if len(chosen) < config.min_photos:
        raise SceneError(
            folder,
            f"holds {len(chosen)} photos ({', '.join(PHOTO_SUFFIXES)}); at least "
            f"{config.min_photos} overlapping photos are needed to find poses",
        )
    if len(chosen) > MAX_PHOTOS:
        raise SceneError(folder, f"holds {len(chosen):,} photos; at most {MAX_PHOTOS:,} are posed")
    return Photos(folder, [_read(p, n) for p, n in chosen], skipped)

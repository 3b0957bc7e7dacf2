"""COLMAP models: sparse/0/{cameras,images,points3D}.{bin,txt} beside an images/ folder, as COLMAP
and nerfstudio's ns-process-data write them. Binary files are little-endian in COLMAP's layout; text
files hold one record a line (two lines an image in images.txt), `#` starting a comment."""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import torch
from torch import Tensor

from model.scenes import values
from model.scenes.errors import SceneError
from model.scenes.formats.jsonfile import read_json
from model.scenes.formats.points import (
    read_colmap_points,
    read_colmap_points_text,
    text_lines,
)
from model.scenes.images import ImageFile, probe_image
from model.scenes.limits import MAX_JSON_BYTES, MAX_POINTS_BYTES, check_file_size
from model.scenes.paths import inside, scene_file
from model.scenes.source import (
    SourceScene,
    SplitBuilder,
    rotate_source,
    scale_intrinsics,
    up_alignment,
)

MODEL = Path("sparse") / "0"
GEOREFERENCE = "georeference.json"
VAL_EVERY = 8  # every 8th image by sorted name is held out, as for LLFF
MAX_IMAGES = 100_000  # registered images (and so cameras) of one model
MAX_NAME_BYTES = 4096
CAMERAS_BYTES = MAX_JSON_BYTES  # one line or 24 + 8 x params bytes a camera
IMAGES_BYTES = MAX_POINTS_BYTES  # images hold their 2D points: thousands an image

# COLMAP's camera model ids (colmap/sensor/models.h), to name the ones refused
MODEL_NAMES = (
    "SIMPLE_PINHOLE",
    "PINHOLE",
    "SIMPLE_RADIAL",
    "RADIAL",
    "OPENCV",
    "OPENCV_FISHEYE",
    "FULL_OPENCV",
    "FOV",
    "SIMPLE_RADIAL_FISHEYE",
    "RADIAL_FISHEYE",
    "THIN_PRISM_FISHEYE",
)
# model -> its parameters in COLMAP's order; k (SIMPLE_RADIAL), k1, k2, p1, p2 become the cameras'
# OpenCV distortion
SUPPORTED = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}
# OpenCV camera axes (x right, y down, z forward) -> OpenGL (right, up, back)
OPENCV_TO_OPENGL = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
QUATERNION_TOLERANCE = 1e-3  # |norm - 1| of a stored rotation; it is then normalised


@dataclass(frozen=True)
class Camera:
    id: int
    model: str
    width: int
    height: int
    intrinsics: Tensor  # fx, fy, cx, cy (float64)
    distortion: Tensor  # OpenCV k1, k2, p1, p2


@dataclass(frozen=True)
class Registered:
    """One image of images.{bin,txt}: its world-to-camera pose (OpenCV axes) and camera."""

    id: int
    qvec: Tensor  # w, x, y, z (unit)
    tvec: Tensor
    camera_id: int
    name: str

    @property
    def label(self) -> str:
        return image_label(self.id, self.name)

    @property
    def where(self) -> str:
        return f" ({self.label})"


def image_label(image_id: int, name: str) -> str:
    """How messages name an image: its id and (a short repr of) its name."""
    return f"image {image_id} {values.describe(name)}"


def check_model(path: Path, camera_id: int, model: str, count: int) -> tuple[str, ...]:
    """The parameter names of a supported model given `count` parameters; else a SceneError."""
    if model not in SUPPORTED:
        raise SceneError(
            path,
            f"camera {camera_id} has model {model}, which is not supported (use one of "
            f"{', '.join(SUPPORTED)})",
        )
    names = SUPPORTED[model]
    if count != len(names):
        raise SceneError(
            path,
            f"camera {camera_id} ({model}) must have {len(names)} parameters "
            f"({' '.join(names)}), got {count}",
        )
    return names


def camera(
    path: Path, camera_id: int, model: str, width: object, height: object, params: list
) -> Camera:
    """A camera of a supported model, every number bounded, its intrinsics checked."""
    where = f" (camera {camera_id})"
    names = check_model(path, camera_id, model, len(params))
    w, h = values.image_size(path, width, height, where)
    p = {
        name: values.number(path, raw, f"parameter {name} of camera {camera_id}")
        for name, raw in zip(names, params)
    }
    fx, fy = p.get("fx", p.get("f")), p.get("fy", p.get("f"))
    intrinsics = torch.tensor([fx, fy, p["cx"], p["cy"]], dtype=torch.float64)
    values.check_intrinsics(path, intrinsics, w, h, where)
    k1 = p.get("k1", p.get("k", 0.0))
    distortion = values.distortion(
        path, [k1, p.get("k2", 0.0), p.get("p1", 0.0), p.get("p2", 0.0)], where
    )
    return Camera(camera_id, model, w, h, intrinsics, distortion)


def registered(
    path: Path, image_id: int, qvec: list, tvec: list, camera_id: int, name: str
) -> Registered:
    if not name:
        raise SceneError(path, f"image {image_id} has an empty name")
    where = f" ({image_label(image_id, name)})"
    q = values.array(path, qvec, f"qvec{where}", ((4,),))
    t = values.array(path, tvec, f"tvec{where}", ((3,),))
    norm = float(q.norm())
    if abs(norm - 1) > QUATERNION_TOLERANCE:
        raise SceneError(
            path, f"qvec{where} must be a unit quaternion (w, x, y, z), its norm is {norm:.3g}"
        )
    return Registered(image_id, q / norm, t, camera_id, name)


def c2w_of(image: Registered) -> Tensor:
    """Camera-to-world (3, 4) float64, OpenGL camera axes, from COLMAP's world-to-camera qvec and
    tvec (OpenCV axes): the centre is -R^T t."""
    w, x, y, z = image.qvec.tolist()
    r = torch.tensor(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ],
        dtype=torch.float64,
    )
    return torch.cat([r.T @ OPENCV_TO_OPENGL, (-r.T @ image.tvec)[:, None]], dim=1)


def unique(path: Path, ids: list[int], what: str) -> None:
    seen: set[int] = set()
    for i in ids:
        if i in seen:
            raise SceneError(path, f"{what} {i} appears twice")
        seen.add(i)


# --- binary -------------------------------------------------------------------------------------


class Cursor:
    """Little-endian fields read in order; running past the end is a truncated file."""

    def __init__(self, path: Path, limit: int):
        check_file_size(path, limit, f"a COLMAP {path.name}")
        self.path, self.data, self.offset = path, path.read_bytes(), 0

    def truncated(self) -> SceneError:
        return SceneError(self.path, f"truncated or malformed COLMAP {self.path.name}")

    def take(self, fmt: str) -> tuple:
        try:
            fields = struct.unpack_from("<" + fmt, self.data, self.offset)
        except struct.error:
            raise self.truncated() from None
        self.offset += struct.calcsize("<" + fmt)
        return fields

    def skip(self, count: int, size: int) -> None:
        if count > (len(self.data) - self.offset) // size:
            raise self.truncated()
        self.offset += count * size

    def count(self, what: str, least: int) -> int:
        """The leading u64 count, no more than the records of `least` bytes the file can hold."""
        (n,) = self.take("Q")
        if n > (len(self.data) - self.offset) // least:
            raise SceneError(
                self.path,
                f"COLMAP {self.path.name} claims {n:,} {what} but holds {len(self.data):,} bytes",
            )
        if n > MAX_IMAGES:
            raise SceneError(
                self.path, f"COLMAP {self.path.name} holds {n:,} {what}; at most {MAX_IMAGES:,}"
            )
        return n

    def name(self) -> bytes:
        end = self.data.find(b"\0", self.offset, self.offset + MAX_NAME_BYTES + 1)
        if end < 0:
            raise self.truncated()
        name, self.offset = self.data[self.offset : end], end + 1
        return name

    def finish(self) -> None:
        if self.offset != len(self.data):
            raise SceneError(
                self.path,
                f"malformed COLMAP {self.path.name}: {len(self.data) - self.offset} trailing bytes",
            )


def read_cameras_bin(path: Path) -> dict[int, Camera]:
    """u64 count, then per camera: u32 camera_id, i32 model_id, u64 width, u64 height, f64
    params."""
    cur = Cursor(path, CAMERAS_BYTES)
    cameras: list[Camera] = []
    for _ in range(cur.count("cameras", 24)):
        camera_id, model_id, width, height = cur.take("IiQQ")
        if not 0 <= model_id < len(MODEL_NAMES) or MODEL_NAMES[model_id] not in SUPPORTED:
            model = MODEL_NAMES[model_id] if 0 <= model_id < len(MODEL_NAMES) else "unknown"
            raise SceneError(
                path,
                f"camera {camera_id} has model {model} (id {model_id}), which is not supported "
                f"(use one of {', '.join(SUPPORTED)})",
            )
        model = MODEL_NAMES[model_id]
        params = list(cur.take(f"{len(SUPPORTED[model])}d"))
        cameras.append(camera(path, camera_id, model, width, height, params))
    cur.finish()
    unique(path, [c.id for c in cameras], "camera id")
    return {c.id: c for c in cameras}


def read_images_bin(path: Path) -> list[Registered]:
    """u64 count, then per image: u32 image_id, f64 qvec[4] (w, x, y, z), f64 tvec[3], u32
    camera_id, a NUL-terminated name, u64 num_points2D and as many (f64 x, f64 y, i64
    point3D_id)."""
    cur = Cursor(path, IMAGES_BYTES)
    images: list[Registered] = []
    for _ in range(cur.count("images", 73)):
        image_id, *pose, camera_id = cur.take("I7dI")
        raw = cur.name()
        (points2d,) = cur.take("Q")
        cur.skip(points2d, 24)
        try:
            name = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise SceneError(path, f"the name of image {image_id} is not UTF-8") from None
        images.append(registered(path, image_id, pose[:4], pose[4:], camera_id, name))
    cur.finish()
    return images


# --- text ---------------------------------------------------------------------------------------


def is_record(line: str) -> bool:
    """Not blank and not a `#` comment."""
    stripped = line.strip()
    return bool(stripped) and not stripped.startswith("#")


def integer(path: Path, text: str, what: str, line: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise SceneError(
            path, f"malformed COLMAP {path.name}: {what} on line {line} is not a whole number"
        ) from None
    return values.integer(path, value, f"{what} (line {line})", 0, 2**32 - 1)


def reals(path: Path, words: list[str], what: str, line: int) -> list[float]:
    try:
        return [float(w) for w in words]
    except ValueError:
        raise SceneError(
            path, f"malformed COLMAP {path.name}: {what} on line {line} are not numbers"
        ) from None


def too_few(path: Path, line: int, got: int, expected: str) -> SceneError:
    return SceneError(
        path,
        f"truncated or malformed COLMAP {path.name}: line {line} has {got} field(s), not "
        f"{expected}",
    )


def read_cameras_txt(path: Path) -> dict[int, Camera]:
    """CAMERA_ID MODEL WIDTH HEIGHT PARAMS[] a line."""
    cameras: list[Camera] = []
    for number, line in text_lines(path, CAMERAS_BYTES, f"a COLMAP {path.name}"):
        if not is_record(line):
            continue
        words = line.split()
        if len(words) < 5:
            raise too_few(path, number, len(words), "CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        if len(cameras) >= MAX_IMAGES:
            raise SceneError(path, f"COLMAP {path.name} holds over {MAX_IMAGES:,} cameras")
        camera_id = integer(path, words[0], "CAMERA_ID", number)
        model = words[1] if len(words[1]) <= values.SHORT else words[1][: values.SHORT] + "..."
        check_model(path, camera_id, model, len(words) - 4)  # before anything is converted
        width = integer(path, words[2], "WIDTH", number)
        height = integer(path, words[3], "HEIGHT", number)
        params = reals(path, words[4:], f"the parameters of camera {camera_id}", number)
        cameras.append(camera(path, camera_id, model, width, height, params))
    unique(path, [c.id for c in cameras], "camera id")
    return {c.id: c for c in cameras}


def read_images_txt(path: Path) -> list[Registered]:
    """Two lines an image: IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then its POINTS2D as (X, Y,
    POINT3D_ID) triples, possibly none (the line is then empty)."""
    lines = text_lines(path, IMAGES_BYTES, f"a COLMAP {path.name}")
    images: list[Registered] = []
    for number, line in lines:
        if not is_record(line):
            continue
        words = line.split(maxsplit=9)
        if len(words) < 10:
            raise too_few(path, number, len(words), "IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        if len(images) >= MAX_IMAGES:
            raise SceneError(path, f"COLMAP {path.name} holds over {MAX_IMAGES:,} images")
        image_id = integer(path, words[0], "IMAGE_ID", number)
        pose = reals(path, words[1:8], f"the pose of image {image_id}", number)
        camera_id = integer(path, words[8], "CAMERA_ID", number)
        # the line after an image's is its POINTS2D, whatever it holds
        points2d = next(lines, None)
        if points2d is None:
            raise SceneError(
                path,
                f"truncated or malformed COLMAP {path.name}: image {image_id} (line {number}) has "
                "no POINTS2D line after it (two lines an image; the second may be empty)",
            )
        if len(points2d[1].split()) % 3:
            raise SceneError(
                path,
                f"truncated or malformed COLMAP {path.name}: the POINTS2D line of image {image_id} "
                f"(line {points2d[0]}) must hold (X, Y, POINT3D_ID) triples",
            )
        images.append(registered(path, image_id, pose[:4], pose[4:], camera_id, words[9].strip()))
    return images


# --- the scene ----------------------------------------------------------------------------------


def model_form(root: Path) -> str:
    """'bin' when the binary cameras and images are present (COLMAP's default), else 'txt'."""
    folder = root / MODEL
    return "bin" if all((folder / f"{f}.bin").is_file() for f in ("cameras", "images")) else "txt"


def view_name(name: str) -> str:
    """The image's name without its suffix, subfolders joined by '_' (names become file names of
    renders)."""
    return PurePosixPath(name).with_suffix("").as_posix().replace("/", "_")


def load_colmap(root: Path, downscale: int) -> SourceScene:
    form = model_form(root)
    cameras_path = scene_file(root, root / MODEL / f"cameras.{form}")
    images_path = scene_file(root, root / MODEL / f"images.{form}")
    cameras = (read_cameras_bin if form == "bin" else read_cameras_txt)(cameras_path)
    images = (read_images_bin if form == "bin" else read_images_txt)(images_path)
    unique(images_path, [im.id for im in images], "image id")
    if not images:
        raise SceneError(images_path, "the model holds no registered images")
    folder = root / "images"
    if not folder.is_dir():
        raise SceneError(
            root, "no images/ folder beside sparse/0 (COLMAP's image names are relative to it)"
        )
    images.sort(key=lambda im: im.name)
    for a, b in zip(images, images[1:]):
        if a.name == b.name:
            raise SceneError(images_path, f"images {a.id} and {b.id} have the same name")

    builders = {"train": SplitBuilder(), "val": SplitBuilder()}
    for i, image in enumerate(images):
        cam = cameras.get(image.camera_id)
        if cam is None:
            raise SceneError(
                images_path,
                f"{image.label} names camera {image.camera_id}, which {cameras_path.name} does "
                "not hold",
            )
        image_path = inside(root, folder / image.name, images_path, f"image name{image.where}")
        if not image_path.is_file():
            raise SceneError(
                image_path, f"image is missing (image {image.id} in {images_path.name})"
            )
        w, h = probe_image(image_path)
        if (w, h) != (cam.width, cam.height):
            raise SceneError(
                image_path,
                f"image is {w}x{h} pixels but camera {cam.id} in {cameras_path.name} says "
                f"{cam.width}x{cam.height} (image {image.id} in {images_path.name})",
            )
        file = ImageFile(image_path, w, h, downscale)
        builders["val" if i % VAL_EVERY == 0 else "train"].add(
            view_name(image.name),
            file,
            scale_intrinsics(cam.intrinsics, file.size, w, h),
            c2w_of(image),
            cam.distortion,
            size=file.size,
            source=images_path,
            where=image.where,
        )

    points = None
    points_path = root / MODEL / f"points3D.{form}"
    if points_path.is_file():
        points_path = scene_file(root, points_path)
        read = read_colmap_points if form == "bin" else read_colmap_points_text
        points = read(points_path)
    source = SourceScene(
        format="colmap",
        root=root,
        splits={name: b.build() for name, b in builders.items() if b.names},
        axes=torch.eye(3),
        units="source units",
        downscale=downscale,
        points=points,
        points_kind="sparse_points" if points is not None else None,
        extras={
            "colmap_model": f"{MODEL.as_posix()} ({'binary' if form == 'bin' else 'text'})",
            "camera_models": sorted({cameras[im.camera_id].model for im in images}),
        },
    )
    georeference = read_georeference(root)
    if georeference is not None:  # east-north-up metres (`leco scene poses` with GPS): z is up
        source.units = "metres"
        source.extras["georeference"] = georeference
        return source
    all_c2w = torch.cat([s.cameras.c2w for s in source.splits.values()])
    return rotate_source(source, up_alignment(all_c2w))


def read_georeference(root: Path) -> dict | None:
    """georeference.json beside sparse/, which `leco scene poses` writes when the photos' GPS
    placed the model in local east-north-up metres; None when there is none."""
    path = root / GEOREFERENCE
    if not path.is_file():
        return None
    info = read_json(scene_file(root, path))
    if not isinstance(info, dict) or info.get("frame") != "ENU" or info.get("units") != "metres":
        raise SceneError(path, 'expected {"frame": "ENU", "units": "metres", ...}')
    origin = info.get("origin")
    if not isinstance(origin, dict) or not all(
        isinstance(origin.get(k), (int, float)) for k in ("latitude", "longitude", "altitude")
    ):
        raise SceneError(path, "origin must give latitude, longitude and altitude as numbers")
    return {
        "frame": "ENU",
        "origin": {k: float(origin[k]) for k in ("latitude", "longitude", "altitude")},
    }

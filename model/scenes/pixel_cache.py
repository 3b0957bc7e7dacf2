"""Decoded training pixels on disk, built once per (scene, split, downscale) and memory-mapped.

Every rank used to hold a concatenated copy of all decoded pixels of its split. A cache is one raw
file of uint8 RGB (`pixels.u8`, 3 bytes a pixel, image after image in the PixelTable's id order) and
a manifest: image sizes, offsets, a CRC-32 per image, and a fingerprint of the source files. Ranks
on one node share it through the page cache, nodes through a shared volume; a rank's own memory is
the pages it touches.

Building is atomic and resumable: the file grows in `<cache>.partial/`, whose `progress.json`
records the images already written and flushed, and the folder is renamed into place only when the
manifest is complete. A cache whose manifest, size or checksums do not match (a crash, a truncated
copy, a flipped bit) is removed and rebuilt; a cache built from other source files (another
fingerprint) is never opened for this scene."""

from __future__ import annotations

import fcntl
import hashlib
import json
import mmap
import os
import shutil
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from model.errors import Failed

VERSION = 1
CHUNK = 16 * 2**20  # bytes per checksum read: bounded memory whatever the image size
# images written between progress records (each one an fsync): a crash redoes at most these
SYNC_EVERY = 32


class PixelCacheError(Failed):
    """A cache that cannot be used; the message says what is wrong with it."""


@dataclass(frozen=True)
class PixelCache:
    folder: Path
    sizes: list[tuple[int, int]]  # (height, width) per image
    offsets: list[int]  # first pixel id of each image, then the total
    pixels: np.ndarray  # (num_pixels, 3) uint8, read-only, over `mapping`
    mapping: mmap.mmap | None  # None for an empty cache

    def __len__(self) -> int:
        return self.offsets[-1]

    def gather(self, pixel: Tensor) -> Tensor:
        """uint8 (B, 3) colours of flat pixel ids; reads only the pages those ids fall in."""
        colours = torch.from_numpy(np.ascontiguousarray(self.pixels[pixel.cpu().numpy()]))
        self.release()
        return colours

    def image(self, index: int) -> Tensor:
        """One whole image, uint8 (H, W, 3), copied out of the map."""
        h, w = self.sizes[index]
        image = torch.from_numpy(
            np.array(self.pixels[self.offsets[index] : self.offsets[index + 1]])
        ).reshape(h, w, 3)
        self.release()
        return image

    def release(self) -> None:
        """Unmap the pages read so far from this process. They stay in the page cache, shared by
        every rank on the node, but no longer count in this process's resident memory: random
        batches over a large cache would otherwise leave a rank's RSS growing towards the size of
        the whole cache."""
        if self.mapping is not None:
            self.mapping.madvise(mmap.MADV_DONTNEED)


def _crc(data: np.ndarray) -> int:
    flat, crc = data.reshape(-1), 0
    for start in range(0, len(flat), CHUNK):
        # .data, not memoryview(array): numpy's stubs declare arrays buffers only from Python 3.12
        # on.
        crc = zlib.crc32(flat[start : start + CHUNK].data, crc)
    return crc


def _file_crcs(path: Path, offsets: list[int]) -> list[int]:
    """The CRC-32 of each image's bytes, read through the file (not the map, whose pages would stay
    resident in this process) in bounded chunks."""
    crcs: list[int] = []
    buffer = bytearray(CHUNK)
    with open(path, "rb", buffering=0) as f:
        for start, end in zip(offsets[:-1], offsets[1:]):
            crc, left = 0, 3 * (end - start)
            while left:
                got = f.readinto(memoryview(buffer)[: min(left, CHUNK)])
                if not got:
                    return crcs
                crc, left = zlib.crc32(memoryview(buffer)[:got], crc), left - got
            crcs.append(crc)
    return crcs


def _map(path: Path, num_pixels: int) -> tuple[np.ndarray, mmap.mmap | None]:
    if num_pixels == 0:
        return np.zeros((0, 3), np.uint8), None
    with open(path, "rb") as f:
        mapping = mmap.mmap(f.fileno(), 3 * num_pixels, access=mmap.ACCESS_READ)
    return np.frombuffer(mapping, dtype=np.uint8).reshape(num_pixels, 3), mapping


def _manifest(folder: Path) -> dict:
    try:
        return json.loads((folder / "manifest.json").read_text())
    except (OSError, ValueError) as error:
        raise PixelCacheError(f"{folder}: no readable manifest ({error})") from None


def open_cache(folder: Path, fingerprint: str, verify: bool = True) -> PixelCache:
    """The finished cache in `folder` if it is whole and was built from sources with this
    fingerprint."""
    folder = Path(folder)
    manifest = _manifest(folder)
    if manifest.get("version") != VERSION or manifest.get("fingerprint") != fingerprint:
        raise PixelCacheError(f"{folder}: built from other sources or by another version")
    sizes = [tuple(s) for s in manifest["sizes"]]
    offsets = [0] + np.cumsum([h * w for h, w in sizes]).tolist()
    path = folder / "pixels.u8"
    if not path.is_file() or path.stat().st_size != 3 * offsets[-1]:
        raise PixelCacheError(
            f"{folder}: pixels.u8 is missing or not {3 * offsets[-1]:,} bytes (truncated?)"
        )
    if verify:
        for i, (crc, found) in enumerate(zip(manifest["crc32"], _file_crcs(path, offsets))):
            if crc != found:
                raise PixelCacheError(
                    f"{folder}: image {i} does not match its checksum (corrupted)"
                )
    return PixelCache(folder, sizes, offsets, *_map(path, offsets[-1]))


def build_cache(
    folder: Path,
    fingerprint: str,
    sizes: list[tuple[int, int]],
    images: Callable[[int], Tensor],
    progress: Callable[[int, int], None] | None = None,
    sync_every: int = SYNC_EVERY,
) -> PixelCache:
    """Writes image i = images(i) (uint8 (H, W, 3), decoded on demand) for every i into a new cache
    at `folder`, resuming a partial build of the same plan, and returns it opened. Progress is
    recorded (after an fsync) every `sync_every` images."""
    folder = Path(folder)
    partial = folder.with_name(folder.name + ".partial")
    plan = {"version": VERSION, "fingerprint": fingerprint, "sizes": [list(s) for s in sizes]}
    done, crcs = _resume(partial, plan)
    total = sum(h * w for h, w in sizes)
    offset = sum(h * w for h, w in sizes[:done])
    # Plain writes, not a map: written pages stay in the page cache, not in the builder's resident
    # memory.
    with open(partial / "pixels.u8", "r+b" if done else "w+b") as f:
        f.truncate(3 * total)
        for i in range(done, len(sizes)):
            image = images(i)
            if tuple(image.shape) != (*sizes[i], 3) or image.dtype != torch.uint8:
                raise PixelCacheError(
                    f"image {i} is {tuple(image.shape)} {image.dtype}; the plan says {sizes[i]} "
                    "uint8"
                )
            block = np.ascontiguousarray(image.reshape(-1, 3).numpy())
            f.seek(3 * offset)
            f.write(block.data.cast("B"))
            crcs.append(_crc(block))
            offset += len(block)
            if len(crcs) % sync_every == 0 or i + 1 == len(sizes):
                f.flush()
                # on disk before progress says so: a crash never leaves a recorded image unwritten
                os.fsync(f.fileno())
                _write_json(partial / "progress.json", {**plan, "crc32": crcs})
            if progress is not None:
                progress(i + 1, len(sizes))
    _write_json(partial / "manifest.json", {**plan, "crc32": crcs})
    (partial / "progress.json").unlink(missing_ok=True)
    if folder.exists():
        shutil.rmtree(folder)  # a stale or corrupt cache this one replaces
    os.replace(partial, folder)  # the whole cache appears at once, or not at all
    return open_cache(folder, fingerprint, verify=False)


def _resume(partial: Path, plan: dict) -> tuple[int, list[int]]:
    """(images already written, their checksums) of a partial build of the same plan, else a fresh
    start."""
    try:
        record = json.loads((partial / "progress.json").read_text())
        if {k: record.get(k) for k in plan} == plan and (partial / "pixels.u8").is_file():
            return len(record["crc32"]), list(record["crc32"])
    except (OSError, ValueError, KeyError, TypeError):
        pass
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    return 0, []


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data))
    os.replace(tmp, path)


def source_fingerprint(root: Path, extra: str) -> str:
    """Every file under the scene folder by path, size and modification time (a stat each: cheap at
    every start, where hashing the contents would read the whole capture; an edited file gets a new
    mtime), plus `extra` (split, scale)."""
    h = hashlib.sha256(extra.encode())
    for path in sorted(p for p in Path(root).rglob("*") if p.is_file()):
        stat = path.stat()
        h.update(f"{path.relative_to(root)}\0{stat.st_size}\0{stat.st_mtime_ns}\n".encode())
    return h.hexdigest()


def ensure_cache(
    cache_dir: Path,
    root: Path,
    split: str,
    downscale: int,
    sizes: list[tuple[int, int]],
    images: Callable[[int], Tensor],
    log: Callable[[str], None] = lambda text: None,
) -> PixelCache:
    """The cache of this scene split at this scale under `cache_dir`: opened when whole and current,
    else built (or its partial build resumed). Ranks that ask at once wait for one builder (a file
    lock), then open it."""
    root = Path(root).resolve()
    fingerprint = source_fingerprint(root, f"{split}:{downscale}")
    key = hashlib.sha256(str(root).encode()).hexdigest()[:16]
    folder = Path(cache_dir) / f"{root.name}-{key}-{split}-x{downscale}"
    try:
        folder.parent.mkdir(parents=True, exist_ok=True)
        lock_file = open(folder.with_name(folder.name + ".lock"), "w")
    except OSError as error:
        raise PixelCacheError(
            f"pixel cache folder {cache_dir} cannot be written ({error.strerror}); set "
            "LECO_PIXEL_CACHE to a writable folder"
        ) from None
    with lock_file as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            return open_cache(folder, fingerprint)
        except PixelCacheError as why:
            if folder.exists() or folder.with_name(folder.name + ".partial").exists():
                log(f"pixel cache {folder.name}: rebuilding ({why})")
        step = max(1, len(sizes) // 20)
        report = lambda done, total: (
            log(f"pixel cache {folder.name}: {done}/{total} images")
            if done % step == 0 or done == total
            else None
        )
        return build_cache(folder, fingerprint, sizes, images, report)

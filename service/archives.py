"""Safe extraction of a user-uploaded dataset archive (tar, tar.gz, tar.bz2, tar.xz or zip).

We never call extractall: every member is first checked (path, type, declared size), and only then
written by hand, one chunk at a time, into a folder we create ourselves, so no link, device or `..`
can reach the disk and a lying header cannot write more than it declared. On any failure the
destination is removed."""

from __future__ import annotations

import lzma
import os
import shutil
import stat
import struct
import tarfile
import zipfile
import zlib
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import IO, Callable, Iterator

from model.errors import InvalidInput


class ArchiveError(InvalidInput):
    """An archive a user uploaded that we refuse, with a message naming the member and what is
    wrong."""


MAX_MEMBERS = 20_000
MAX_TOTAL_BYTES = 2 * 2**30  # uncompressed, all members together
MAX_RATIO = 200  # uncompressed / compressed: beyond it we call it a zip bomb
MAX_DEPTH = 32  # folders in a member's path
# a member's whole path (PATH_MAX is 4096), and 255 per component
MAX_PATH_BYTES = 1024
# the central directory zipfile parses whole when it opens a zip
MAX_ZIP_DIRECTORY_BYTES = 64 * 2**20

CHUNK = 1 << 20
# What a broken archive raises while we read it. tarfile and zipfile wrap only part of it: gzip and
# lzma raise their own errors, bz2 reports bad data as a bare OSError. Only reads are wrapped (see
# _reading), so a full disk on our side is never blamed on the upload.
CORRUPT = (tarfile.TarError, zipfile.BadZipFile, EOFError, zlib.error, lzma.LZMAError, OSError)
# Leading bytes of gzip, bzip2, xz and zip: such a file that neither tarfile nor zipfile opens is
# broken, not something else (a zip cut short loses the directory at its end, so is_zipfile says
# no).
ARCHIVE_MAGIC = (b"\x1f\x8b", b"BZh", b"\xfd7zXZ\x00", b"PK\x03\x04")
ZIP_METHODS = {zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA}


@dataclass(frozen=True)
class Entry:
    name: str  # as stored in the archive, for messages
    is_dir: bool
    size: int  # declared uncompressed size
    open: Callable[[], IO[bytes]]
    parts: tuple[str, ...] = ()  # the checked relative path, filled in by _plan


@dataclass(frozen=True)
class Limits:
    members: int
    total_bytes: int
    ratio: float
    archive_size: int

    def check_total(self, name: str, total: int, verb: str) -> None:
        if total > self.total_bytes:
            raise _refuse(name, f"archive {verb} more than {self.total_bytes:,} bytes uncompressed")
        if total > self.ratio * self.archive_size:
            raise _refuse(
                name,
                f"archive {verb} {total:,} bytes from {self.archive_size:,} on disk (more than "
                f"{self.ratio:g}x): looks like a zip bomb",
            )


def extract_archive(
    archive: Path,
    dest: Path,
    *,
    max_members: int = MAX_MEMBERS,
    max_total_bytes: int = MAX_TOTAL_BYTES,
    max_ratio: float = MAX_RATIO,
) -> Path:
    """Extracts `archive` into `dest` (which must not exist yet; it is created) and returns the
    scene root: the single top-level folder when the archive holds exactly one (ignoring macOS
    `__MACOSX` and `.DS_Store` junk), else `dest`. On any error it raises ArchiveError and removes
    `dest` entirely: nothing half-written."""
    archive, dest = Path(archive), Path(dest)
    limits = Limits(max_members, max_total_bytes, max_ratio, archive.stat().st_size)
    # FileExistsError before the try: never remove a folder that was not ours
    dest.mkdir(parents=True)
    try:
        with _reading():
            handle, entries = _open_archive(archive, limits)
        with handle:
            with _reading():
                plan = _plan(entries, limits)
            _extract(plan, dest, limits)
    except BaseException:
        shutil.rmtree(dest, ignore_errors=True)
        raise
    tops = list(dest.iterdir())  # junk was never written, so it cannot hide a single top folder
    return tops[0] if len(tops) == 1 and tops[0].is_dir() else dest


def _open_archive(
    archive: Path, limits: Limits
) -> tuple[tarfile.TarFile | zipfile.ZipFile, Iterator[Entry]]:
    # Tar first: is_zipfile looks for a zip directory near the end, which a plain tar whose last
    # member is a .zip also has; a tar header's checksum cannot pass on a zip's first bytes.
    if tarfile.is_tarfile(archive):
        tar = tarfile.open(archive, "r:*")
        return tar, _tar_entries(tar, limits)
    if zipfile.is_zipfile(archive):
        _check_zip_directory(archive, limits)
        zf = zipfile.ZipFile(archive)
        return zf, _zip_entries(zf)
    with archive.open("rb") as f:
        head = f.read(8)
    if head.startswith(ARCHIVE_MAGIC):
        raise ArchiveError(
            "archive is truncated or corrupt: it starts like one but cannot be opened"
        )
    raise ArchiveError("not a tar or zip archive")


def _tar_entries(tar: tarfile.TarFile, limits: Limits) -> Iterator[Entry]:
    for info in tar:  # lazily, so a member-count bomb stops at max_members + 1
        if info.issym():
            raise _refuse(info.name, f"symbolic links are not allowed (to {info.linkname!r})")
        if info.islnk():
            raise _refuse(info.name, f"hard links are not allowed (to {info.linkname!r})")
        if info.ischr() or info.isblk():
            raise _refuse(info.name, "device files are not allowed")
        if info.isfifo():
            raise _refuse(info.name, "FIFOs are not allowed")
        if not (info.isreg() or info.isdir()):
            raise _refuse(info.name, f"not a regular file or a folder (tar type {info.type!r})")
        yield Entry(
            info.name, info.isdir(), info.size if info.isreg() else 0, _tar_opener(tar, info)
        )
    # tarfile stops at its end marker; reading on to the end lets gzip and xz check their CRCs, so a
    # flipped byte in the data is refused here, before anything is written. Whatever follows the end
    # marker is decompressed too, so every byte of the stream counts against the limits (153 bytes
    # of bzip2 can hide 64 MiB of zeros there).
    stream = tar.fileobj
    while stream.read(CHUNK):
        limits.check_total("(data after the last member)", stream.tell(), "decompresses to")


def _tar_opener(tar: tarfile.TarFile, info: tarfile.TarInfo) -> Callable[[], IO[bytes]]:
    def open_member() -> IO[bytes]:
        src = tar.extractfile(info)
        if src is None:  # tarfile gives a reader to every regular file, and only those are opened
            raise _refuse(info.name, "not a regular file")
        return src

    return open_member


def _check_zip_directory(archive: Path, limits: Limits) -> None:
    """Reads the end-of-central-directory record (zip64's too) ourselves, so a directory claiming
    millions of entries or gigabytes is refused before zipfile parses it whole into memory."""
    with archive.open("rb") as f:
        f.seek(0, os.SEEK_END)
        size = f.tell()
        f.seek(max(0, size - (22 + 65535)))
        tail = f.read()
        at = tail.rfind(b"PK\x05\x06")
        if at < 0 or len(tail) - at < 22:
            return  # zipfile will call it corrupt
        _, _, _, _, entries, directory, _, _ = struct.unpack("<4s4H2LH", tail[at : at + 22])
        locator = tail[at - 20 : at] if at >= 20 else b""
        if (entries == 0xFFFF or directory == 0xFFFFFFFF) and locator.startswith(b"PK\x06\x07"):
            f.seek(struct.unpack("<4sLQL", locator)[2])
            record = f.read(56)
            if len(record) == 56 and record.startswith(b"PK\x06\x06"):
                entries, directory = struct.unpack("<4sQ2H2L4Q", record)[7:9]
    if entries > limits.members:
        raise ArchiveError(
            f"zip directory lists {entries:,} members; the limit is {limits.members:,}"
        )
    if directory > MAX_ZIP_DIRECTORY_BYTES:
        raise ArchiveError(
            f"zip directory is {directory:,} bytes; the limit is {MAX_ZIP_DIRECTORY_BYTES:,}"
        )


def _zip_entries(zf: zipfile.ZipFile) -> Iterator[Entry]:
    for info in zf.infolist():
        kind = stat.S_IFMT(info.external_attr >> 16)  # Unix type bits; 0 when the zipper set none
        if stat.S_ISLNK(kind):
            raise _refuse(info.filename, "symbolic links are not allowed")
        if kind and not (stat.S_ISREG(kind) or stat.S_ISDIR(kind)):
            raise _refuse(info.filename, f"not a regular file or a folder (mode {kind:#o})")
        if info.flag_bits & 0x1:
            raise _refuse(info.filename, "encrypted members are not supported")
        if info.compress_type not in ZIP_METHODS:
            raise _refuse(info.filename, f"unsupported compression method {info.compress_type}")
        is_dir = info.is_dir() or stat.S_ISDIR(kind)
        yield Entry(info.filename, is_dir, 0 if is_dir else info.file_size, partial(zf.open, info))


def _plan(entries: Iterator[Entry], limits: Limits) -> list[Entry]:
    """Checks every member before anything is written: count, path, and the declared sizes."""
    plan, declared = [], 0
    for count, entry in enumerate(entries, 1):
        if count > limits.members:
            raise _refuse(entry.name, f"archive holds more than {limits.members:,} members")
        parts = _safe_parts(entry.name)
        if not parts and not entry.is_dir:
            raise _refuse(entry.name, "file has no name")
        declared += entry.size
        limits.check_total(entry.name, declared, "declares")
        plan.append(Entry(entry.name, entry.is_dir, entry.size, entry.open, parts))
    if not any(not e.is_dir and not _is_junk(e.parts) for e in plan):
        raise ArchiveError("archive holds no files")
    return plan


def _safe_parts(name: str) -> tuple[str, ...]:
    # Backslashes count as separators: Windows zippers write them, and `..\x` must not slip through.
    if name.startswith(("/", "\\")) or (len(name) >= 2 and name[1] == ":" and name[0].isalpha()):
        raise _refuse(name, "path is absolute")
    parts = tuple(p for p in name.replace("\\", "/").split("/") if p not in ("", "."))
    if ".." in parts:
        raise _refuse(name, "path leaves the archive ('..')")
    shown = name if len(name) <= 200 else name[:200] + "..."
    if len(parts) > MAX_DEPTH:
        raise _refuse(shown, f"path is {len(parts)} folders deep; the limit is {MAX_DEPTH}")
    if len(name.encode()) > MAX_PATH_BYTES or any(len(p.encode()) > 255 for p in parts):
        raise _refuse(
            shown, f"path is longer than {MAX_PATH_BYTES} bytes or has a name over 255 bytes"
        )
    return parts


def _is_junk(parts: tuple[str, ...]) -> bool:
    # Finder's metadata: the __MACOSX tree, .DS_Store, and AppleDouble `._name` files beside real
    # ones.
    return bool(parts) and (
        parts[0] == "__MACOSX" or parts[-1] == ".DS_Store" or parts[-1].startswith("._")
    )


def _extract(plan: list[Entry], dest: Path, limits: Limits) -> None:
    written = 0
    for entry in plan:
        if _is_junk(entry.parts):
            continue
        target = dest.joinpath(*entry.parts)
        _make_dirs(entry, target if entry.is_dir else target.parent)
        if not entry.is_dir:
            written = _write_file(entry, target, written, limits)


def _make_dirs(entry: Entry, folder: Path) -> None:
    try:
        # only folders we made ourselves: no links to follow
        folder.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise _refuse(entry.name, "path clashes with a file extracted earlier") from None


def _write_file(entry: Entry, target: Path, written: int, limits: Limits) -> int:
    """Copies one member in chunks; returns the bytes written so far, all members together."""
    # O_EXCL: a duplicate member cannot overwrite, O_NOFOLLOW: never through a link; 0o644 whatever
    # the archive says (no setuid, no executables).
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
    try:
        fd = os.open(target, flags, 0o644)
    except FileExistsError:
        raise _refuse(entry.name, "path appears twice or clashes with a folder") from None
    with os.fdopen(fd, "wb") as out:
        with _reading(entry.name):
            src = entry.open()
        size = 0
        while True:
            with _reading(entry.name):
                chunk = src.read(CHUNK)
            if not chunk:
                return written
            # Headers can lie: hold each member to its declared size and everything to the limits.
            size += len(chunk)
            written += len(chunk)
            if size > entry.size:
                raise _refuse(
                    entry.name, f"holds more than the {entry.size:,} bytes its header declares"
                )
            limits.check_total(entry.name, written, "expands to")
            out.write(chunk)


@contextmanager
def _reading(name: str | None = None) -> Iterator[None]:
    """Turns what a truncated or corrupt archive raises while being read into an ArchiveError."""
    try:
        yield
    except CORRUPT as exc:
        where = f"member {name!r}: " if name else ""
        raise ArchiveError(f"{where}archive is truncated or corrupt: {exc}") from exc


def _refuse(name: str, reason: str) -> ArchiveError:
    return ArchiveError(f"member {name!r}: {reason}")

"""Safe extraction of an uploaded dataset archive (tar, tar.gz/bz2/xz, zip). Every member is checked
before a byte is written: no absolute paths, no `..`, no links, no devices; member count, total size and
compression ratio are bounded (zip bombs), and the bytes actually written are counted too (headers lie).
Files are written one by one by us, never by extractall. On any error `dest` is removed: nothing half-written."""

from __future__ import annotations

import shutil
import stat
import tarfile
import zipfile
import zlib
from pathlib import Path, PurePosixPath

MAX_MEMBERS = 20_000
MAX_TOTAL_BYTES = 2 * 2**30  # uncompressed, all members together
MAX_RATIO = 200  # uncompressed / compressed: beyond it we call it a zip bomb
CHUNK = 1 << 20
JUNK = ("__MACOSX", ".DS_Store")


class ArchiveError(ValueError):
    """An uploaded archive we refuse, with the member and the reason."""


def safe_name(name: str) -> PurePosixPath:
    clean = name.replace("\\", "/")
    path = PurePosixPath(clean)
    if clean.startswith("/") or (len(clean) > 1 and clean[1] == ":"):
        raise ArchiveError(f"member {name!r}: absolute path")
    if ".." in path.parts:
        raise ArchiveError(f"member {name!r}: path leaves the archive ('..')")
    return PurePosixPath(*[p for p in path.parts if p not in ("", ".")])


def _members(archive: Path):
    """(name, kind, declared size, opener) for every member; kind is 'file' or 'dir'."""
    if zipfile.is_zipfile(archive):
        with zipfile.ZipFile(archive) as zf:
            for info in zf.infolist():
                kind = stat.S_IFMT(info.external_attr >> 16)  # 0 when the writer recorded no Unix type
                if kind == stat.S_IFLNK:
                    raise ArchiveError(f"member {info.filename!r}: symbolic links are not allowed")
                if kind not in (0, stat.S_IFREG, stat.S_IFDIR):
                    raise ArchiveError(f"member {info.filename!r}: not a regular file or folder")
                yield info.filename, "dir" if info.is_dir() else "file", info.file_size, (lambda i=info: zf.open(i))
        return
    if tarfile.is_tarfile(archive):
        with tarfile.open(archive) as tf:
            for info in tf:
                if info.issym() or info.islnk():
                    raise ArchiveError(f"member {info.name!r}: links are not allowed")
                if not (info.isfile() or info.isdir()):
                    raise ArchiveError(f"member {info.name!r}: devices, FIFOs and special files are not allowed")
                yield info.name, "dir" if info.isdir() else "file", info.size, (lambda i=info: tf.extractfile(i))
        return
    raise ArchiveError("not a tar or zip archive")


def extract_archive(archive: Path, dest: Path, *, max_members: int = MAX_MEMBERS,
                    max_total_bytes: int = MAX_TOTAL_BYTES, max_ratio: float = MAX_RATIO) -> Path:
    """Extracts into `dest` (created; must not exist) and returns the scene root: the single top-level folder
    when there is exactly one, else `dest`."""
    archive, dest = Path(archive), Path(dest)
    limit = min(max_total_bytes, max_ratio * max(archive.stat().st_size, 1))
    dest.mkdir(parents=True)
    try:
        count, written, files = 0, 0, 0
        for name, kind, declared, opener in _members(archive):
            count += 1
            if count > max_members:
                raise ArchiveError(f"more than {max_members} members")
            relative = safe_name(name)
            if not relative.parts or relative.parts[0] in JUNK or relative.name in JUNK:
                continue
            target = dest.joinpath(*relative.parts)
            if kind == "dir":
                target.mkdir(parents=True, exist_ok=True)
                continue
            if written + declared > limit:
                raise ArchiveError(f"member {name!r}: archive expands beyond {limit:,} bytes (zip bomb?)")
            target.parent.mkdir(parents=True, exist_ok=True)
            with opener() as source, open(target, "xb") as out:
                while chunk := source.read(CHUNK):
                    written += len(chunk)
                    if written > limit:
                        raise ArchiveError(f"member {name!r}: archive expands beyond {limit:,} bytes (zip bomb?)")
                    out.write(chunk)
            files += 1
        if files == 0:
            raise ArchiveError("the archive holds no files")
    except ArchiveError:
        shutil.rmtree(dest, ignore_errors=True)
        raise
    except FileExistsError as error:
        shutil.rmtree(dest, ignore_errors=True)
        raise ArchiveError(f"member {Path(error.filename).name!r} appears twice") from None
    except (tarfile.TarError, zipfile.BadZipFile, EOFError, zlib.error, OSError, RuntimeError) as error:
        shutil.rmtree(dest, ignore_errors=True)
        raise ArchiveError(f"archive is truncated or corrupt: {error}") from None
    top = [p for p in dest.iterdir()]
    return top[0] if len(top) == 1 and top[0].is_dir() else dest

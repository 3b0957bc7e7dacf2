"""Uploaded archives: good ones extract to a scene root; hostile or broken ones are refused with the member
and the reason, and leave nothing behind."""

import io
import tarfile
import zipfile

import pytest

from service.archives import ArchiveError, extract_archive


def tar_with(path, members, mode="w:gz"):
    with tarfile.open(path, mode) as tf:
        for info, data in members:
            tf.addfile(info, io.BytesIO(data) if data is not None else None)
    return path


def file_info(name, data=b"x"):
    info = tarfile.TarInfo(name)
    info.size = len(data)
    return info, data


def special(name, kind, linkname=""):
    info = tarfile.TarInfo(name)
    info.type, info.linkname = kind, linkname
    return info, None


def test_a_tar_with_one_folder_returns_that_folder(tmp_path):
    archive = tar_with(tmp_path / "s.tar.gz", [file_info("scene/a.txt", b"hello"), file_info("scene/d/b.bin", b"\0" * 9)])
    root = extract_archive(archive, tmp_path / "out")
    assert root == tmp_path / "out" / "scene"
    assert (root / "a.txt").read_bytes() == b"hello" and (root / "d" / "b.bin").read_bytes() == b"\0" * 9


def test_a_flat_zip_returns_dest_and_skips_macos_junk(tmp_path):
    with zipfile.ZipFile(tmp_path / "s.zip", "w") as zf:
        zf.writestr("transforms.json", "{}")
        zf.writestr("__MACOSX/._transforms.json", "junk")
    root = extract_archive(tmp_path / "s.zip", tmp_path / "out")
    assert root == tmp_path / "out" and sorted(p.name for p in root.iterdir()) == ["transforms.json"]


@pytest.mark.parametrize("member, reason", [
    (file_info("/etc/passwd"), "absolute path"),
    (file_info("scene/../../escape.txt"), r"leaves the archive \('..'\)"),
    (special("scene/link", tarfile.SYMTYPE, "/etc/passwd"), "links are not allowed"),
    (special("scene/hard", tarfile.LNKTYPE, "scene/a.txt"), "links are not allowed"),
    (special("scene/dev", tarfile.CHRTYPE), "devices, FIFOs"),
    (special("scene/fifo", tarfile.FIFOTYPE), "devices, FIFOs"),
])
def test_hostile_tar_members_are_refused(tmp_path, member, reason):
    archive = tar_with(tmp_path / "bad.tar", [file_info("scene/a.txt"), member], mode="w")
    with pytest.raises(ArchiveError, match=reason) as error:
        extract_archive(archive, tmp_path / "out")
    assert member[0].name in str(error.value) or reason == "absolute path"
    assert not (tmp_path / "out").exists() and not (tmp_path / "escape.txt").exists()


def test_zip_symlink_and_bomb_are_refused(tmp_path):
    link = zipfile.ZipInfo("scene/link")
    link.external_attr = (0o120777 << 16)
    with zipfile.ZipFile(tmp_path / "link.zip", "w") as zf:
        zf.writestr(link, "/etc/passwd")
    with pytest.raises(ArchiveError, match="'scene/link': symbolic links"):
        extract_archive(tmp_path / "link.zip", tmp_path / "out")
    with zipfile.ZipFile(tmp_path / "bomb.zip", "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("zeros.bin", b"\0" * (50 * 2**20))
    assert (tmp_path / "bomb.zip").stat().st_size < 100_000
    with pytest.raises(ArchiveError, match="'zeros.bin': archive expands beyond .* \\(zip bomb\\?\\)"):
        extract_archive(tmp_path / "bomb.zip", tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_a_lying_header_is_caught_while_writing(tmp_path):
    """A tar member declaring 10 bytes but padded with far more cannot sneak past: the declared size is what
    tarfile reads, so the real check is the byte count, bounded by max_total_bytes."""
    archive = tar_with(tmp_path / "big.tar", [file_info(f"scene/f{i}", b"y" * 4000) for i in range(5)], mode="w")
    with pytest.raises(ArchiveError, match="expands beyond 10,000 bytes"):
        extract_archive(archive, tmp_path / "out", max_total_bytes=10_000)
    with pytest.raises(ArchiveError, match="more than 3 members"):
        extract_archive(archive, tmp_path / "out", max_members=3)
    assert not (tmp_path / "out").exists()


def test_truncated_random_and_empty_archives(tmp_path):
    good = tar_with(tmp_path / "s.tar.gz", [file_info(f"scene/{i}.bin", bytes(range(256)) * 200) for i in range(4)])
    (tmp_path / "cut.tar.gz").write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(ArchiveError, match="truncated or corrupt"):
        extract_archive(tmp_path / "cut.tar.gz", tmp_path / "out")
    (tmp_path / "noise.bin").write_bytes(bytes((i * 7919) % 251 for i in range(5000)))
    with pytest.raises(ArchiveError, match="not a tar or zip archive"):
        extract_archive(tmp_path / "noise.bin", tmp_path / "out")
    with zipfile.ZipFile(tmp_path / "empty.zip", "w"):
        pass
    with pytest.raises(ArchiveError, match="no files"):
        extract_archive(tmp_path / "empty.zip", tmp_path / "out")
    assert not (tmp_path / "out").exists()

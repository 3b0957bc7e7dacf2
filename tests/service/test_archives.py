"""Uploaded archives: good ones extract to a scene root; hostile or broken ones are refused with the
member and the reason, and leave nothing behind (the destination is gone, nothing appeared anywhere
else)."""

import io
import random
import stat
import struct
import tarfile
import zipfile

import pytest

from service.archives import ArchiveError, extract_archive

TAR_MODES = ["w", "w:gz", "w:bz2", "w:xz"]


def noise(n, seed=0):
    return random.Random(seed).randbytes(n)


def file_info(name, data=b"x", mode=0o644):
    info = tarfile.TarInfo(name)
    info.size, info.mode = len(data), mode
    return info, data


def special(name, kind, linkname=""):
    info = tarfile.TarInfo(name)
    info.type, info.linkname = kind, linkname
    return info, None


def make_tar(path, members, mode="w:gz"):
    with tarfile.open(path, mode) as tf:
        for info, data in members:
            tf.addfile(info, io.BytesIO(data) if data is not None else None)
    return path


def make_zip(path, members, compression=zipfile.ZIP_STORED):
    with zipfile.ZipFile(path, "w", compression) as zf:
        for name_or_info, data in members:
            zf.writestr(name_or_info, data)
    return path


def refused(archive, tmp_path, **limits):
    """Extracts into tmp_path/work/out and returns the ArchiveError's message, after checking that
    the destination is gone and nothing else under tmp_path changed: a `../x` member would land in
    work/."""
    (tmp_path / "work").mkdir(exist_ok=True)
    before = sorted(tmp_path.rglob("*"))
    dest = tmp_path / "work" / "out"
    with pytest.raises(ArchiveError) as error:
        extract_archive(archive, dest, **limits)
    assert not dest.exists()
    assert sorted(tmp_path.rglob("*")) == before
    return str(error.value)


# --- good archives
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", TAR_MODES)
def test_a_tar_with_one_top_folder_returns_it_with_the_same_bytes(tmp_path, mode):
    files = {"scene/transforms.json": b'{"frames": []}', "scene/images/r_0.png": noise(70_000)}
    folder = tarfile.TarInfo("scene")
    folder.type = tarfile.DIRTYPE
    members = [
        (folder, None),
        file_info("scene/transforms.json", files["scene/transforms.json"]),
        file_info("./scene/images/r_0.png", files["scene/images/r_0.png"], mode=0o4777),
        file_info("__MACOSX/scene/._r_0.png", b"junk"),
        file_info("scene/.DS_Store", b"junk"),
        file_info("._scene", b"junk"),
    ]
    # the type is found by content, not by name
    archive = make_tar(tmp_path / "upload.bin", members, mode)

    root = extract_archive(archive, tmp_path / "out")

    assert root == tmp_path / "out" / "scene"
    written = {
        str(p.relative_to(tmp_path / "out")): p
        for p in (tmp_path / "out").rglob("*")
        if p.is_file()
    }
    assert sorted(written) == sorted(files)  # the macOS junk was not written
    for name, data in files.items():
        assert written[name].read_bytes() == data
        # no setuid, no exec from the archive
        assert stat.S_IMODE(written[name].stat().st_mode) & ~0o644 == 0


def test_a_zip_with_files_at_the_top_returns_dest(tmp_path):
    archive = make_zip(
        tmp_path / "upload.tar.gz",
        [
            ("transforms.json", b"{}"),
            ("images/r_0.png", noise(5000)),
            ("__MACOSX/._transforms.json", b"junk"),
        ],
        zipfile.ZIP_DEFLATED,
    )
    root = extract_archive(archive, tmp_path / "out")
    assert root == tmp_path / "out"
    assert sorted(p.name for p in root.iterdir()) == ["images", "transforms.json"]
    assert (root / "images" / "r_0.png").read_bytes() == noise(5000)


def test_a_tar_whose_last_member_is_a_zip_is_read_as_a_tar(tmp_path):
    inner = make_zip(tmp_path / "inner.zip", [("x.txt", b"x")]).read_bytes()
    archive = make_tar(tmp_path / "s.tar", [file_info("scene/extra.zip", inner)], "w")
    root = extract_archive(archive, tmp_path / "out")
    assert (root / "extra.zip").read_bytes() == inner


def test_an_existing_destination_is_refused_and_left_alone(tmp_path):
    archive = make_tar(tmp_path / "s.tar.gz", [file_info("scene/a.txt")])
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError):
        extract_archive(archive, tmp_path / "out")
    assert (tmp_path / "out" / "keep.txt").read_text() == "mine"


# --- hostile paths and member types
# -----------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["tar", "zip"])
@pytest.mark.parametrize(
    "name, reason",
    [
        ("/etc/passwd", "path is absolute"),
        ("C:\\Windows\\evil.dll", "path is absolute"),
        ("\\\\server\\share\\evil", "path is absolute"),
        ("../escape.txt", "path leaves the archive ('..')"),
        ("scene/../../escape.txt", "path leaves the archive ('..')"),
        ("scene\\..\\..\\escape.txt", "path leaves the archive ('..')"),
    ],
)
def test_hostile_paths_are_refused(tmp_path, kind, name, reason):
    members = [("scene/a.txt", b"ok"), (name, b"evil")]
    if kind == "tar":
        archive = make_tar(tmp_path / "bad", [file_info(n, d) for n, d in members])
    else:
        archive = make_zip(tmp_path / "bad", members)
    assert refused(archive, tmp_path) == f"member {name!r}: {reason}"


@pytest.mark.parametrize(
    "member, reason",
    [
        (
            special("scene/link", tarfile.SYMTYPE, "/etc/passwd"),
            "symbolic links are not allowed (to '/etc/passwd')",
        ),
        (
            special("scene/hard", tarfile.LNKTYPE, "scene/a.txt"),
            "hard links are not allowed (to 'scene/a.txt')",
        ),
        (special("scene/tty", tarfile.CHRTYPE), "device files are not allowed"),
        (special("scene/disk", tarfile.BLKTYPE), "device files are not allowed"),
        (special("scene/fifo", tarfile.FIFOTYPE), "FIFOs are not allowed"),
        # contiguous file: a regular file to tarfile, accepted
        (special("scene/cont", tarfile.CONTTYPE), None),
    ],
)
def test_tar_links_devices_and_fifos_are_refused(tmp_path, member, reason):
    archive = make_tar(tmp_path / "bad.tar", [file_info("scene/a.txt"), member], "w")
    if reason is None:
        assert extract_archive(archive, tmp_path / "out").name == "scene"
        return
    assert refused(archive, tmp_path) == f"member {member[0].name!r}: {reason}"


@pytest.mark.parametrize(
    "mode, reason",
    [
        (stat.S_IFLNK | 0o777, "symbolic links are not allowed"),
        (stat.S_IFIFO | 0o644, "not a regular file or a folder (mode 0o10000)"),
        (stat.S_IFCHR | 0o644, "not a regular file or a folder (mode 0o20000)"),
    ],
)
def test_zip_links_and_specials_marked_in_external_attr_are_refused(tmp_path, mode, reason):
    link = zipfile.ZipInfo("scene/link")
    link.external_attr = mode << 16
    archive = make_zip(tmp_path / "link.zip", [("scene/a.txt", b"ok"), (link, b"/etc/passwd")])
    assert refused(archive, tmp_path) == f"member 'scene/link': {reason}"


def test_an_encrypted_zip_member_is_refused(tmp_path):
    raw = bytearray(
        make_zip(
            tmp_path / "plain.zip", [("scene/secret.bin", b"not really encrypted")]
        ).read_bytes()
    )
    # zipfile cannot write encrypted members: set the flag bit by hand
    raw[raw.find(b"PK\x03\x04") + 6] |= 0x1
    raw[raw.find(b"PK\x01\x02") + 8] |= 0x1
    (tmp_path / "enc.zip").write_bytes(bytes(raw))
    assert (
        refused(tmp_path / "enc.zip", tmp_path)
        == "member 'scene/secret.bin': encrypted members are not supported"
    )


@pytest.mark.parametrize("second", ["scene/a.txt", "scene/a.txt/b.txt"])
def test_a_duplicate_or_clashing_member_is_refused(tmp_path, second):
    archive = make_tar(
        tmp_path / "dup.tar", [file_info("scene/a.txt", b"1"), file_info(second, b"2")], "w"
    )
    assert refused(archive, tmp_path).startswith(f"member {second!r}: path ")


# --- sizes: member count, totals, zip bombs, lying headers
# ------------------------------------------------


@pytest.mark.parametrize("kind", ["tar", "zip"])
def test_too_many_members_are_refused(tmp_path, kind):
    members = [(f"scene/f{i}.txt", b"x") for i in range(5)]
    archive = (
        make_tar(tmp_path / "many", [file_info(n, d) for n, d in members])
        if kind == "tar"
        else make_zip(tmp_path / "many", members)
    )
    expected = (
        "member 'scene/f3.txt': archive holds more than 3 members"
        if kind == "tar"
        # zip: from its end record, before parsing
        else "zip directory lists 5 members; the limit is 3"
    )
    assert refused(archive, tmp_path, max_members=3) == expected
    assert extract_archive(archive, tmp_path / "ok", max_members=5).name == "scene"


def test_a_zip_bomb_is_refused_at_the_default_ratio(tmp_path):
    with zipfile.ZipFile(tmp_path / "bomb.zip", "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("zeros.bin", "w") as out:
            for _ in range(50):
                out.write(bytes(2**20))
    size = (tmp_path / "bomb.zip").stat().st_size
    assert size < 100_000
    message = refused(tmp_path / "bomb.zip", tmp_path)
    assert message == (
        f"member 'zeros.bin': archive declares {50 * 2**20:,} bytes from {size:,} on disk (more "
        "than 200x): looks like a zip bomb"
    )


def test_the_total_size_limit_is_enforced(tmp_path):
    archive = make_tar(
        tmp_path / "big.tar", [file_info(f"scene/f{i}", noise(4000, i)) for i in range(5)], "w"
    )
    assert (
        refused(archive, tmp_path, max_total_bytes=10_000)
        == "member 'scene/f2': archive declares more than 10,000 bytes uncompressed"
    )


def test_a_zip_whose_header_understates_the_size_is_refused(tmp_path):
    """Both headers claim 10 bytes for 64 KiB: zipfile stops at 10, the CRC cannot match, we
    refuse."""
    raw = bytearray(
        make_zip(
            tmp_path / "good.zip", [("data.bin", noise(65536))], zipfile.ZIP_DEFLATED
        ).read_bytes()
    )
    local, central = raw.find(b"PK\x03\x04"), raw.find(b"PK\x01\x02")
    struct.pack_into("<I", raw, local + 22, 10)  # local header: uncompressed size
    struct.pack_into("<I", raw, central + 24, 10)  # central directory: uncompressed size
    (tmp_path / "liar.zip").write_bytes(bytes(raw))
    message = refused(tmp_path / "liar.zip", tmp_path)
    assert message.startswith("member 'data.bin': archive is truncated or corrupt: Bad CRC-32")


def test_a_member_stream_longer_than_its_header_is_cut_off(tmp_path, monkeypatch):
    """tarfile and zipfile never read past a declared size, so the byte count while writing is a
    second line: a reader that did (a future tarfile, another backend) still cannot write more than
    was declared."""
    archive = make_tar(tmp_path / "s.tar", [file_info("scene/a.txt", b"0123456789")], "w")
    monkeypatch.setattr(
        tarfile.TarFile, "extractfile", lambda self, member: io.BytesIO(bytes(4096))
    )
    assert (
        refused(archive, tmp_path)
        == "member 'scene/a.txt': holds more than the 10 bytes its header declares"
    )


# --- broken, foreign and empty archives
# --------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["tar.gz", "tar.xz", "zip"])
def test_a_truncated_archive_is_refused(tmp_path, kind):
    # incompressible: the cut lands in data
    members = [(f"scene/{i}.bin", noise(64_000, i)) for i in range(4)]
    if kind == "zip":
        good = make_zip(tmp_path / "good", members, zipfile.ZIP_DEFLATED)
    else:
        good = make_tar(tmp_path / "good", [file_info(n, d) for n, d in members], "w:" + kind[4:])
    (tmp_path / "cut").write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    assert "archive is truncated or corrupt: " in refused(tmp_path / "cut", tmp_path)


def test_random_bytes_are_not_an_archive(tmp_path):
    (tmp_path / "noise.tar.gz").write_bytes(noise(4096, seed=7))
    assert refused(tmp_path / "noise.tar.gz", tmp_path) == "not a tar or zip archive"


@pytest.mark.parametrize("kind", ["tar", "zip"])
def test_an_archive_without_files_is_refused(tmp_path, kind):
    if kind == "tar":
        archive = make_tar(tmp_path / "empty.tar.gz", [special("scene", tarfile.DIRTYPE)])
    else:
        archive = make_zip(tmp_path / "empty.zip", [("scene/", b""), ("scene/.DS_Store", b"junk")])
    assert refused(archive, tmp_path) == "archive holds no files"


# --- Bombs behind the end marker, huge zip directories, deep paths
# -----------------------------------------


@pytest.mark.parametrize("mode", ["w:bz2", "w:gz", "w:xz"])
def test_data_after_the_tar_end_marker_counts_against_the_limits(tmp_path, mode):
    import bz2
    import gzip
    import lzma

    plain = io.BytesIO()
    with tarfile.open(fileobj=plain, mode="w") as tf:
        info, data = file_info("scene/a.txt", b"hello")
        tf.addfile(info, io.BytesIO(data))
    stream = plain.getvalue() + bytes(64 * 2**20)  # 64 MiB of zeros after the end marker
    compress = {"w:bz2": bz2.compress, "w:gz": gzip.compress, "w:xz": lzma.compress}[mode]
    (tmp_path / "bomb").write_bytes(compress(stream))
    assert (tmp_path / "bomb").stat().st_size < 70_000
    message = refused(tmp_path / "bomb", tmp_path)
    assert message.startswith("member '(data after the last member)': archive decompresses to")
    assert message.endswith("looks like a zip bomb")


def test_a_zip_directory_listing_too_many_members_is_refused_before_it_is_parsed(tmp_path):
    archive = make_zip(tmp_path / "many.zip", [(f"scene/f{i}.txt", b"x") for i in range(5)])
    # A directory that claims 2**32 - 2 bytes: the end record is read, not the directory.
    data = bytearray(archive.read_bytes())
    end = data.rfind(b"PK\x05\x06")
    data[end + 12 : end + 16] = struct.pack("<L", 0xFFFFFFFE)
    (tmp_path / "huge.zip").write_bytes(bytes(data))
    assert refused(tmp_path / "huge.zip", tmp_path).startswith(
        "zip directory is 4,294,967,294 bytes; the limit is"
    )


@pytest.mark.parametrize("kind", ["tar", "zip"])
def test_deep_and_long_member_paths_are_refused_with_a_message_not_a_crash(tmp_path, kind):
    deep = "scene/" + "d/" * 1300 + "f.txt"
    long = "scene/" + "n" * 300 + ".txt"
    for name, reason in (
        (deep, "folders deep; the limit is 32"),
        (long, "has a name over 255 bytes"),
    ):
        archive = (
            make_tar(tmp_path / f"a-{len(name)}", [file_info(name)], "w")
            if kind == "tar"
            else make_zip(tmp_path / f"a-{len(name)}", [(name, b"x")])
        )
        message = refused(archive, tmp_path)
        assert reason in message and len(message) < 400

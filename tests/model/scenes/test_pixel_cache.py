"""The memory-mapped pixel cache: exact contents, atomic and resumable builds, corruption and
changed sources detected and rebuilt, one builder among concurrent ranks."""

import json
import os
import tempfile
import threading
from pathlib import Path

import pytest
import torch

from model.scenes.pixel_cache import PixelCacheError, build_cache, ensure_cache, open_cache
from model.scenes.rays import PixelTable
from tests.model.scenes.test_rays import AABB, small_views

SIZES = [(6, 8), (5, 7), (9, 4), (3, 3)]


def images_for(sizes, seed=0):
    g = torch.Generator().manual_seed(seed)
    return [torch.randint(0, 256, (h, w, 3), generator=g, dtype=torch.uint8) for h, w in sizes]


def test_a_store_holds_exactly_the_images_in_pixel_id_order(tmp_path):
    images = images_for(SIZES)
    cache = build_cache(tmp_path / "s", "fp", SIZES, lambda i: images[i])
    flat = torch.cat([im.reshape(-1, 3) for im in images])
    assert len(cache) == len(flat) and torch.equal(cache.gather(torch.arange(len(flat))), flat)
    ids = torch.tensor([5, 0, len(flat) - 1, 5])
    assert torch.equal(cache.gather(ids), flat[ids])
    assert all(torch.equal(cache.image(i), images[i]) for i in range(len(images)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]  # no partial folder left behind
    reopened = open_cache(tmp_path / "s", "fp")
    assert torch.equal(reopened.gather(ids), flat[ids])
    with pytest.raises(PixelCacheError, match="other sources"):
        open_cache(tmp_path / "s", "another fingerprint")


def test_an_interrupted_build_is_never_used_and_resumes_where_it_stopped(tmp_path):
    images, calls = images_for(SIZES), []

    def failing(i):
        calls.append(i)
        if i == 2:
            raise KeyboardInterrupt  # the process dies while decoding the third image
        return images[i]

    with pytest.raises(KeyboardInterrupt):
        build_cache(tmp_path / "s", "fp", SIZES, failing, sync_every=1)
    assert not (tmp_path / "s").exists() and (tmp_path / "s.partial").is_dir()
    with pytest.raises(PixelCacheError, match="no readable manifest"):
        open_cache(tmp_path / "s", "fp")
    calls.clear()
    cache = build_cache(tmp_path / "s", "fp", SIZES, lambda i: calls.append(i) or images[i])
    assert calls == [2, 3]  # the two images written before the crash are not decoded again
    assert all(torch.equal(cache.image(i), images[i]) for i in range(len(images)))
    # a partial build of another plan is discarded, not resumed
    (tmp_path / "t.partial").mkdir()
    (tmp_path / "t.partial" / "progress.json").write_text(
        '{"version": 1, "fingerprint": "old", "crc32": [1]}'
    )
    calls.clear()
    build_cache(tmp_path / "t", "fp", SIZES, lambda i: calls.append(i) or images[i])
    assert calls == [0, 1, 2, 3]


def test_a_corrupted_or_truncated_store_is_detected_and_rebuilt(tmp_path):
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "a.png").write_bytes(b"source")
    images, messages = images_for(SIZES), []
    ensure = lambda: ensure_cache(
        tmp_path / "cache", scene, "train", 1, SIZES, lambda i: images[i], messages.append
    )
    cache = ensure()
    path = cache.folder / "pixels.u8"
    data = bytearray(path.read_bytes())
    data[3 * 6 * 8 + 5] ^= 0xFF  # a flipped byte in the second image (the first is 6 x 8 pixels)
    path.write_bytes(bytes(data))
    fingerprint = json.loads((cache.folder / "manifest.json").read_text())["fingerprint"]
    with pytest.raises(PixelCacheError, match="image 1 does not match its checksum"):
        open_cache(cache.folder, fingerprint)
    rebuilt = ensure()
    assert any("rebuilding" in m and "checksum" in m for m in messages)
    assert torch.equal(rebuilt.image(1), images[1])
    path.write_bytes(path.read_bytes()[:-3])  # a copy cut short
    messages.clear()
    assert torch.equal(ensure().image(3), images[3])
    assert any("truncated" in m for m in messages)


def test_changed_sources_or_another_scale_get_their_own_cache(tmp_path):
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "a.png").write_bytes(b"source")
    first, second = images_for(SIZES, 0), images_for(SIZES, 1)
    cache = tmp_path / "cache"
    a = ensure_cache(cache, scene, "train", 1, SIZES, lambda i: first[i])
    # reused
    assert torch.equal(
        ensure_cache(cache, scene, "train", 1, SIZES, lambda i: second[i]).image(0), first[0]
    )
    (scene / "a.png").write_bytes(b"edited")  # a source changed: the old pixels must not be served
    os.utime(scene / "a.png", ns=(1, 1))
    b = ensure_cache(cache, scene, "train", 1, SIZES, lambda i: second[i])
    assert b.folder == a.folder and torch.equal(b.image(0), second[0])
    half = [(h // 2 or 1, w // 2 or 1) for h, w in SIZES]
    c = ensure_cache(cache, scene, "train", 2, half, lambda i: images_for(half)[i])
    assert c.folder != a.folder and c.sizes == half


def test_concurrent_ranks_wait_for_one_builder(tmp_path):
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "a.png").write_bytes(b"source")
    images, builds, caches = images_for(SIZES), [], []

    def decode(i):
        builds.append(i)
        return images[i]

    ranks = [
        threading.Thread(
            target=lambda: caches.append(
                ensure_cache(tmp_path / "cache", scene, "train", 1, SIZES, decode)
            )
        )
        for _ in range(3)
    ]
    for t in ranks:
        t.start()
    for t in ranks:
        t.join()
    assert builds == [0, 1, 2, 3] and len(caches) == 3  # each image decoded once, by one rank


def test_pixel_table_reads_the_same_rays_from_a_cache():
    views = small_views()
    sizes = [(int(h), int(w)) for h, w in zip(views.cameras.height, views.cameras.width)]
    with tempfile.TemporaryDirectory() as tmp:
        cache = build_cache(Path(tmp) / "s", "fp", sizes, lambda i: views.images[i])
        ids = torch.randperm(views.num_pixels, generator=torch.Generator().manual_seed(0))[:40]
        plain, mapped = PixelTable(views).rays(ids, AABB), PixelTable(views, cache).rays(ids, AABB)
        assert torch.equal(plain.rgb, mapped.rgb) and torch.equal(plain.origins, mapped.origins)
        other = build_cache(Path(tmp) / "o", "fp", sizes[:2], lambda i: views.images[i])
        with pytest.raises(ValueError, match="other image sizes"):
            PixelTable(views, other)


def test_an_unwritable_cache_is_named_with_the_setting_to_change(tmp_path):
    (tmp_path / "a-file").write_text("not a folder")
    with pytest.raises(
        PixelCacheError, match=r"cache folder .*a-file cannot be written .*set LECO_PIXEL_CACHE"
    ):
        ensure_cache(
            tmp_path / "a-file", tmp_path, "train", 1, SIZES, lambda i: images_for(SIZES)[i]
        )


def test_an_image_corrupted_inside_is_found_when_the_store_decodes_it(tmp_path, monkeypatch):
    """Loading reads headers and the file's end only; a damaged body shows when its pixels are
    decoded, and the build stops naming the file, leaving no cache to be used."""
    from model.scenes import load_scene
    from model.scenes.errors import SceneError
    from model.scenes.synthetic import generate
    from workers.pixels import attach_pixel_caches

    monkeypatch.setenv("LECO_PIXEL_CACHE", str(tmp_path / "cache"))
    generate("tiny", 0, tmp_path / "scene")
    victim = sorted((tmp_path / "scene" / "train" / "rgbs").iterdir())[3]
    data = bytearray(victim.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 16] = bytes(16)  # header and IEND intact
    victim.write_bytes(bytes(data))
    scene = load_scene(tmp_path / "scene")
    with pytest.raises(SceneError, match=rf"{victim.name}: image is unreadable"):
        attach_pixel_caches(scene, ("train",))
    assert not list((tmp_path / "cache").glob("*/manifest.json"))  # no finished cache to be used


def resident_file_kb() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("RssFile:"):
            return int(line.split()[1])
    pytest.skip("this kernel does not report RssFile in /proc/self/status")


def test_reading_a_store_leaves_its_pages_out_of_the_process_resident_memory(tmp_path):
    """Random batches touch every page of a large cache; a rank's RSS must stay its batch plus its
    model (the pages stay in the page cache, shared by the ranks of a node)."""
    sizes = [(1024, 1024)] * 24  # 72 MiB
    image = torch.randint(
        0, 256, (1024, 1024, 3), generator=torch.Generator().manual_seed(0), dtype=torch.uint8
    )
    cache = build_cache(tmp_path / "big", "fp", sizes, lambda i: image)
    before = resident_file_kb()
    g = torch.Generator().manual_seed(1)
    for _ in range(64):  # 64 x 4096 random pixels: nearly every one of the 18,432 pages
        colours = cache.gather(torch.randint(0, len(cache), (4096,), generator=g))
    assert colours.shape == (4096, 3)
    assert torch.equal(cache.image(5), image)
    grown_mb = (resident_file_kb() - before) / 1024
    assert grown_mb < 8, f"the cache's pages stayed resident: {grown_mb:.0f} MiB"

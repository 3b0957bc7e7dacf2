"""The scale scene built small: views are crops of shared renders, and a crop is an exact image of
its camera (the principal point shifted by its offset), so crops of one render agree pixel for
pixel. Loading it reads headers only; its pixels reach a run through the cache, one image decoded at
a time."""

from dataclasses import replace

import pytest
import torch

from model.scenes import load_scene
from model.scenes.frames import LazyFrames
from model.scenes.pixel_cache import ensure_cache
from model.scenes.rays import PixelTable
from model.scenes.synthetic import PRESETS, generate
from model.scenes.synthetic.writer import crop_offsets

SMALL_XL = replace(
    PRESETS["xl"], blocks=2, views=24, width=48, height=36, crops_per_render=6, val_every=8
)


@pytest.fixture(scope="module")
def small_xl(tmp_path_factory):
    out = tmp_path_factory.mktemp("xl") / "xl-small"
    summary = generate(SMALL_XL, 5, out)
    return out, summary


def test_the_scale_preset_is_the_size_the_issue_asks_for():
    xl = PRESETS["xl"]
    assert xl.views >= 2000 and xl.width >= 640 and xl.height >= 480 and not xl.depth_maps


def test_crops_of_one_render_are_exact_views_of_their_cameras(small_xl):
    out, summary = small_xl
    assert summary["views"] == {"train": 21, "val": 3}
    assert not (out / "gt" / "depth").exists()  # the preset writes no depth maps
    scene = load_scene(out)
    assert scene.bounds.source == "camera_axes" and isinstance(scene.train.images, LazyFrames)
    views = {
        name: (split, i) for split in scene.splits.values() for i, name in enumerate(split.names)
    }
    offsets = crop_offsets(SMALL_XL, 5, 4)
    assert len({tuple(o) for o in offsets.reshape(-1, 2).tolist()}) > 12  # the crops really differ
    for render in range(4):
        first, second = (views[f"{render * 6 + k:06d}"] for k in (0, 1))
        (dx0, dy0), (dx1, dy1) = offsets[render, 0], offsets[render, 1]
        # Pixel (u, v) of crop 0 is pixel (u + dx0 - dx1, v + dy0 - dy1) of crop 1, where both hold
        # it.
        a, b = first[0].image(first[1]), second[0].image(second[1])
        u0, v0 = max(0, dx1 - dx0), max(0, dy1 - dy0)
        u1, v1 = min(48, 48 + dx1 - dx0), min(36, 36 + dy1 - dy0)
        assert u1 - u0 >= 8 and v1 - v0 >= 8
        overlap_a = a[v0:v1, u0:u1]
        overlap_b = b[v0 + dy0 - dy1 : v1 + dy0 - dy1, u0 + dx0 - dx1 : u1 + dx0 - dx1]
        assert torch.equal(overlap_a, overlap_b)
        # ... and the two cameras cast the same ray through those pixels.
        cams_a, cams_b = first[0].cameras, second[0].cameras
        assert torch.equal(cams_a.c2w[first[1]], cams_b.c2w[second[1]])
        assert torch.allclose(
            cams_a.intrinsics[first[1], 2:] + torch.tensor([dx0, dy0], dtype=torch.float32),
            cams_b.intrinsics[second[1], 2:] + torch.tensor([dx1, dy1], dtype=torch.float32),
        )


def test_loading_decodes_nothing_and_the_store_decodes_each_image_once(
    small_xl, tmp_path, monkeypatch
):
    out, _ = small_xl
    decoded = []
    import model.scenes.images as images

    real = images.read_image
    monkeypatch.setattr(
        images, "read_image", lambda path, **kw: decoded.append(path.name) or real(path, **kw)
    )
    scene = load_scene(out)
    assert decoded == []  # headers only
    views = scene.train
    sizes = [(int(h), int(w)) for h, w in zip(views.cameras.height, views.cameras.width)]
    cache = ensure_cache(tmp_path, out, "train", 1, sizes, lambda i: views.images[i])
    assert sorted(decoded) == sorted(f"{name}.png" for name in views.names)  # one decode per image
    views.cache = cache
    table = PixelTable(views)
    pixel = torch.tensor([0, 5, len(table) - 1])
    assert table.cache is cache and torch.equal(table.colours(pixel), cache.gather(pixel))
    assert torch.equal(views.image(3), views.images[3])

"""An upload under 1 MiB may declare at most MAX_PIXELS_PER_UPLOAD_BYTE pixels per byte
(service/scenes.py); the largest image it could hold is decoded here in a fresh interpreter, and the
decode must grow the process by less than 256 MB at its peak, whether the PNG is RGB or RGBA
(composited in blocks, model/scenes/images.py)."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from service.scenes import MAX_PIXELS_PER_UPLOAD_BYTE

UPLOAD_BYTES = 1 << 20
LIMIT_MB = 256

MEASURE = """
import json, sys
from pathlib import Path
from model.scenes.images import read_image

def status_kb(field):
    for line in open("/proc/self/status"):
        if line.startswith(field + ":"):
            return int(line.split()[1])

# The imports peaked higher than the process now holds: reset the high-water mark
# (Linux: 5 > clear_refs) so the peak read after the decode is the decode's own.
with open("/proc/self/clear_refs", "w") as f:
    f.write("5")
before = status_kb("VmRSS")
image = read_image(Path(sys.argv[1]), background=(1.0, 1.0, 1.0))
peak = status_kb("VmHWM")
grew_mb = (peak - before) / 1024
print(json.dumps({"grew_mb": grew_mb, "shape": list(image.shape), "pixel": image[0, 0].tolist()}))
"""


@pytest.mark.parametrize("mode", ["RGB", "RGBA"])
def test_the_largest_image_a_small_upload_may_declare_decodes_within_256_mb(tmp_path, mode):
    side = math.isqrt(MAX_PIXELS_PER_UPLOAD_BYTE * UPLOAD_BYTES)
    colour = (200, 100, 50, 128)[: len(mode)]
    path = tmp_path / "giant.png"
    Image.new(mode, (side, side), colour).save(path)
    # one colour compresses: the file fits the small upload
    assert path.stat().st_size < UPLOAD_BYTES
    done = subprocess.run(
        [sys.executable, "-c", MEASURE, str(path)], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    measured = json.loads(done.stdout)
    assert measured["shape"] == [side, side, 3]
    expected = (
        colour[:3]
        if mode == "RGB"
        else [round(c * 128 / 255 + 255 * (1 - 128 / 255)) for c in colour[:3]]
    )
    assert measured["pixel"] == list(expected)
    print(
        f"{mode} {side}x{side} ({path.stat().st_size:,} bytes): the decode grew the process by "
        f"{measured['grew_mb']:.0f} MB"
    )
    assert measured["grew_mb"] < LIMIT_MB, (
        f"decoding {side}x{side} {mode} grew the process too much"
    )


def test_blocks_composite_exactly_as_the_whole_image_would(monkeypatch):
    import model.scenes.images as images

    rng = np.random.default_rng(0)
    rgba = rng.integers(0, 256, (37, 11, 4), dtype=np.uint8)
    whole = rgba.astype(np.float32) / 255.0
    alpha = whole[..., 3:]
    reference = np.clip(
        np.round((whole[..., :3] * alpha + np.float32(0.5) * (1 - alpha)) * 255), 0, 255
    )
    for block in (1, 11 * 5, 1 << 18):  # a row at a time, several rows, the whole image
        monkeypatch.setattr(images, "COMPOSITE_BLOCK_PIXELS", block)
        assert np.array_equal(images._composite(rgba, (0.5, 0.5, 0.5)), reference.astype(np.uint8))

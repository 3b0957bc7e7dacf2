"""The validation view that sees the most sky, rendered by each finished run given: does a method's
far field show a sky between the training views? (docs/RESULTS.md's village figure.)

    python -m bench.sky_figure --runs RUN [RUN ...] --out FIGURE.png [--view NAME]

Each run is a `leco train` or `leco bench` run folder; they must share a scene. The view is the
validation view whose ground-truth depth is infinite (sky) on the most pixels, unless named. A row a
run: its prediction, the ground truth and the prediction's absolute error, with the view's PSNR."""

from __future__ import annotations

import argparse
import math
from pathlib import Path


def sky_view(views) -> int:
    """The index of the view with the most sky pixels (infinite depth)."""
    if views.depth is None:
        raise ValueError("the scene has no ground-truth depth: name the view with --view")
    shares = [float((~d.isfinite()).float().mean()) for d in views.depth]
    return max(range(len(shares)), key=shares.__getitem__)


def main(argv: list[str] | None = None) -> int:
    import numpy as np
    import torch
    from PIL import Image, ImageDraw

    from model.methods import get_method
    from workers.render.frames import appearance_row, render_frame
    from workers.renderer import to_uint8
    from workers.trained import load_run

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", nargs="+", required=True, help="run folders")
    parser.add_argument("--out", required=True, help="the PNG to write")
    parser.add_argument("--view", default=None, help="a validation view's name")
    parser.add_argument("--scale", type=int, default=3, help="pixels a rendered pixel")
    args = parser.parse_args(argv)
    rows = []
    for run in args.runs:
        trained = load_run(run)
        views = trained.scene.splits["val"]
        index = views.names.index(args.view) if args.view else sky_view(views)
        with torch.no_grad():
            frame = render_frame(trained, views.cameras, index, appearance_row(trained, "mean"))
        predicted = to_uint8(frame.rgb).numpy()
        truth = views.image(index).numpy()
        error = np.abs(predicted.astype(np.int16) - truth.astype(np.int16)).astype(np.uint8)
        mse = float(np.mean((predicted / 255.0 - truth / 255.0) ** 2))
        psnr = -10 * math.log10(max(mse, 1e-10))
        name = get_method(trained.cfg.method).label
        label = f"{name} ({Path(run).name}): {psnr:.2f} dB on view {views.names[index]}"
        rows.append((label, np.concatenate([predicted, truth, error], axis=1)))
        print(label)
    height, width = rows[0][1].shape[:2]
    s, band = args.scale, 16
    figure = Image.new("RGB", (width * s, len(rows) * (height * s + band)), "white")
    draw = ImageDraw.Draw(figure)
    for k, (label, image) in enumerate(rows):
        top = k * (height * s + band)
        draw.text((4, top + 2), label + "  (prediction | ground truth | error)", fill="black")
        tile = Image.fromarray(image).resize((width * s, height * s), Image.Resampling.NEAREST)
        figure.paste(tile, (0, top + band))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    figure.save(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""`leco bench-render`: render time per method. Render the same camera path with several finished
runs (LeCO, vanilla, the grid, ... on one scene) and print seconds per frame, rays/s and the
main-network samples each method spent per ray; also one viewer preview per size. Every k-th frame
of the path is timed (the vanilla method takes tens of seconds a frame on a CPU; the path and the
frames timed are the same for every run), after one untimed warm-up frame; runs are timed one after
another in this process, threads fixed."""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path


def time_run(
    run: str,
    path_cfg: dict,
    frames: int,
    size: tuple[int, int],
    every: int,
    previews: list[tuple[int, int]],
) -> dict:
    from workers.render.frames import appearance_row, render_frame
    from workers.render.job import build_path
    from workers.render.schemas import RenderConfig
    from workers.trained import load_run

    trained = load_run(run)
    cfg = RenderConfig(width=size[0], height=size[1], frames=frames, path=path_cfg)
    cameras = build_path(cfg, trained.scene).cameras()
    row = appearance_row(trained, "mean")
    render_frame(trained, cameras, 0, row)  # warm-up: allocator, lazy imports
    seconds, samples = [], []
    for i in range(0, frames, every):
        started = time.perf_counter()
        frame = render_frame(trained, cameras, i, row)
        seconds.append(time.perf_counter() - started)
        samples.append(frame.samples_per_ray)
    views = {}
    for w, h in previews:
        small = build_path(
            RenderConfig(width=w, height=h, frames=frames, path=path_cfg), trained.scene
        ).cameras()
        started = time.perf_counter()
        render_frame(trained, small, 0, row)
        views[f"{w}x{h}"] = time.perf_counter() - started
    return {
        "run": run,
        "method": trained.cfg.method,
        "frames_timed": len(seconds),
        "seconds_per_frame": statistics.fmean(seconds),
        "min_seconds_per_frame": min(seconds),
        "max_seconds_per_frame": max(seconds),
        "rays_per_s": size[0] * size[1] * len(seconds) / sum(seconds),
        "samples_per_ray": statistics.fmean(samples),
        "view_seconds": views,
    }


def bench_render_command(args: argparse.Namespace) -> int:
    import torch

    torch.set_num_threads(args.threads)
    w, _, h = args.size.partition("x")
    path_cfg = {"kind": args.path}
    results = [
        time_run(run, path_cfg, args.frames, (int(w), int(h)), args.every, [(160, 120), (320, 240)])
        for run in args.run
    ]
    fastest = min(r["seconds_per_frame"] for r in results)
    for r in results:
        r["slower_than_fastest"] = r["seconds_per_frame"] / fastest
    report = {
        "path": args.path,
        "frames": args.frames,
        "size": args.size,
        "every": args.every,
        "threads": args.threads,
        "results": results,
    }
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=1))
    print(
        f"{args.path}, {args.frames} frames of {args.size}, every {args.every}th timed, "
        f"{args.threads} threads"
    )
    print(
        f"{'method':10} {'s/frame':>8} {'rays/s':>9} {'samples/ray':>11} {'x fastest':>9} "
        f"{'view 160x120':>12} {'view 320x240':>12}"
    )
    for r in results:
        v = r["view_seconds"]
        print(
            f"{r['method']:10} {r['seconds_per_frame']:8.2f} {r['rays_per_s']:9,.0f} "
            f"{r['samples_per_ray']:11.1f} {r['slower_than_fastest']:9.2f} {v['160x120']:12.2f} "
            f"{v['320x240']:12.2f}"
        )
    return 0


def add_commands(commands) -> None:
    bench = commands.add_parser(
        "bench-render", help="seconds per frame of finished runs along one camera path"
    )
    bench.add_argument(
        "--run", action="append", required=True, help="a finished run folder; repeat to compare"
    )
    bench.add_argument("--path", default="orbit", choices=["orbit", "flyover", "spiral"])
    bench.add_argument("--frames", type=int, default=120)
    bench.add_argument("--size", default="320x240")
    bench.add_argument(
        "--every", type=int, default=10, help="time every k-th frame of the path (default 10)"
    )
    bench.add_argument(
        "--threads", type=int, default=2, help="torch threads (default 2: this machine's cores)"
    )
    bench.add_argument("--out", default=None, help="write the numbers as JSON here")
    bench.set_defaults(func=bench_render_command)

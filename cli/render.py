"""`leco render` and `leco export`: videos along a camera path and geometry in the dataset's frame,
from a finished run folder. The service runs the same code as render and export jobs."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from workers.render.camera_paths.registry import PATH_KINDS, generated


def path_spec(args: argparse.Namespace) -> dict:
    """A generated path with the options given (those its kind has), or a user's file: nerfstudio's
    camera_path.json, a {"cameras": [...]} file (what a render writes as NAME.camera_path.json), or
    a bare list of matrices."""
    if args.path in generated():
        options = {
            "pitch_deg": args.pitch,
            "altitude": args.altitude,
            "turns": args.turns,
            "fov_deg": args.fov,
        }
        fields = PATH_KINDS[args.path].model_fields
        return {
            "kind": args.path,
            **{k: v for k, v in options.items() if v is not None and k in fields},
        }
    file = Path(args.path)
    if not file.is_file():
        raise FileNotFoundError(
            f"--path {args.path}: neither {', '.join(generated())} nor a camera path file"
        )
    data = json.loads(file.read_text())
    if isinstance(data, list):
        return {"kind": "cameras", "cameras": [{"c2w": m} for m in data]}
    if "camera_path" in data:
        return {**data, "kind": "nerfstudio"}
    if "cameras" in data:
        return {
            k: v for k, v in data.items() if k in ("kind", "frame", "width", "height", "cameras")
        } | {"kind": "cameras"}
    raise ValueError(
        f"{file}: not a camera path (expected nerfstudio's camera_path.json, a 'cameras' list, or "
        "a list of camera-to-world matrices)"
    )


def render_command(args: argparse.Namespace) -> int:
    from workers.render.job import render_video
    from workers.render.schemas import RenderConfig
    from workers.trained import load_run

    width, _, height = args.size.partition("x")
    cfg = RenderConfig(
        width=int(width),
        height=int(height or 0),
        frames=args.frames,
        fps=args.fps,
        appearance=args.appearance if args.appearance == "mean" else int(args.appearance),
        depth_video=args.depth_video,
        path=path_spec(args),
    )
    trained = load_run(args.run)
    progress = (
        (lambda text: print(f"\r[render] {text}", end="", file=sys.stderr, flush=True))
        if sys.stderr.isatty()
        else (lambda text: None)
    )
    summary = render_video(trained, cfg, Path(args.out), log=progress)
    if sys.stderr.isatty():
        print(file=sys.stderr)
    print(json.dumps(summary, indent=2))
    return 0


def export_command(args: argparse.Namespace) -> int:
    from workers.render.export import export
    from workers.render.schemas import ExportConfig
    from workers.trained import load_run

    cfg = ExportConfig(
        what=args.what,
        stride=args.stride,
        min_opacity=args.min_opacity,
        max_points=args.max_points,
        resolution=args.resolution,
    )
    out = Path(args.out) if args.out else Path(args.run) / "export"
    print(json.dumps(export(load_run(args.run), cfg, out), indent=2))
    return 0


def add_commands(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    render = commands.add_parser(
        "render", help="an H.264 video of a finished run along a camera path"
    )
    render.add_argument("--run", required=True, help="run folder written by leco train")
    render.add_argument(
        "--path",
        default="orbit",
        help=f"{' | '.join(generated())} | FILE (nerfstudio camera_path.json, a 'cameras' JSON, or "
        "a list of 3x4/4x4 camera-to-world matrices; in the dataset's own frame)",
    )
    render.add_argument(
        "--frames", type=int, default=120, help="frames of a generated path (default 120)"
    )
    render.add_argument("--size", default="320x240", help="WxH, both even (default 320x240)")
    render.add_argument("--fps", type=float, default=24.0)
    render.add_argument(
        "--out",
        required=True,
        help="the MP4 to write; NAME.poster.png, NAME.camera_path.json and NAME.render.json go "
        "beside it",
    )
    render.add_argument(
        "--appearance",
        default="mean",
        help="'mean' of the training views' embeddings (default) or a training image's index",
    )
    render.add_argument("--depth-video", action="store_true", help="also NAME.depth.mp4")
    render.add_argument(
        "--pitch", type=float, default=None, help="orbit: degrees below the horizon (default 30)"
    )
    render.add_argument(
        "--altitude",
        type=float,
        default=None,
        help="orbit: above the box centre, in the dataset's units (default: the box fills the "
        "view)",
    )
    render.add_argument("--turns", type=float, default=None, help="orbit (1) or spiral (2): turns")
    render.add_argument("--fov", type=float, default=None, help="vertical field of view in degrees")
    render.set_defaults(func=render_command)

    exp = commands.add_parser(
        "export", help="geometry of a finished run in the dataset's own frame and units"
    )
    exp.add_argument("what", choices=["pointcloud", "cameras", "occupancy"])
    exp.add_argument("--run", required=True, help="run folder written by leco train")
    exp.add_argument(
        "--out", default=None, help="folder (default RUN/export); transform.json is written beside"
    )
    exp.add_argument(
        "--stride", type=int, default=1, help="pointcloud: every n-th pixel (default 1)"
    )
    exp.add_argument(
        "--min-opacity", type=float, default=0.9, help="pointcloud: opacity a ray needs (0.9)"
    )
    exp.add_argument(
        "--max-points", type=int, default=1_000_000, help="pointcloud: seeded subsample beyond"
    )
    exp.add_argument(
        "--resolution", type=int, default=128, help="occupancy: grid cells per side (128)"
    )
    exp.set_defaults(func=export_command)

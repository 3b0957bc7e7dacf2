"""The `leco` command line. Subcommands import their layer lazily so `leco scene ...` stays
light."""

from __future__ import annotations

import argparse
import json
import sys
import time


def scene_synth(args: argparse.Namespace) -> int:
    from model.scenes.synthetic import generate

    started = time.perf_counter()
    summary = generate(args.preset, args.seed, args.out)
    summary.setdefault("seconds", round(time.perf_counter() - started, 2))
    print(json.dumps(summary, indent=2, default=str))
    return 0


def scene_info(args: argparse.Namespace) -> int:
    from model.scenes import load_scene
    from model.scenes.info import describe, format_info

    info = describe(load_scene(args.path, downscale=args.downscale))
    print(json.dumps(info, indent=2) if args.json else format_info(info))
    return 0


def model_info_command(args: argparse.Namespace) -> int:
    from model.model_info import format_model_info, model_info
    from model.profiles import get_profile

    info = model_info(args.method, get_profile(args.profile), args.images)
    print(json.dumps(info, indent=2) if args.json else format_model_info(info))
    return 0


def build_parser() -> argparse.ArgumentParser:
    # read when the parser is built, so a method registered before counts
    from model.methods import METHODS

    parser = argparse.ArgumentParser(
        prog="leco", description="LeCO-NeRF service: scenes, training, benchmarks."
    )
    commands = parser.add_subparsers(dest="command", required=True)

    scene = commands.add_parser("scene", help="generate, pose or inspect scenes").add_subparsers(
        dest="action", required=True
    )
    synth = scene.add_parser(
        "synth", help="generate a synthetic city with exact ground truth (Mega-NeRF format + gt/)"
    )
    synth.add_argument(
        "--preset",
        default="city",
        help="tiny | city | village | large | xl (default: city; village is countryside flown low, "
        "seeing the horizon; xl is the 2,000-view scale scene: 640x480, about 1 GB on disk and 5 "
        "minutes to write)",
    )
    synth.add_argument("--seed", type=int, default=0)
    synth.add_argument("--out", required=True, help="output folder (must not exist or be empty)")
    synth.set_defaults(func=scene_synth)

    info = scene.add_parser("info", help="describe a scene folder of any supported format")
    info.add_argument("path")
    info.add_argument("--json", action="store_true", help="print JSON instead of text")
    info.add_argument("--downscale", type=int, default=None, help="integer image downscale factor")
    info.set_defaults(func=scene_info)

    from cli.poses import add_poses_command

    add_poses_command(scene)

    model = commands.add_parser("model", help="inspect model sizes").add_subparsers(
        dest="action", required=True
    )
    minfo = model.add_parser(
        "info", help="parameter count of every component of a method under a profile"
    )
    minfo.add_argument("--method", default="leco", help=" | ".join(METHODS))
    minfo.add_argument("--profile", default="paper", help="paper | cpu | smoke")
    minfo.add_argument(
        "--images", type=int, default=100, help="images in the scene (appearance embeddings)"
    )
    minfo.add_argument("--json", action="store_true")
    minfo.set_defaults(func=model_info_command)

    from bench.cli import add_commands as add_bench_commands
    from bench.load import add_commands as add_load_commands
    from bench.memory import add_commands as add_memory_commands
    from bench.render_speed import add_commands as add_render_bench_commands
    from bench.scale import add_commands as add_scale_commands
    from bench.step_profile import add_commands as add_step_commands
    from cli.render import add_commands as add_render_commands
    from cli.results import add_commands as add_results_commands
    from cli.serve import add_commands as add_service_commands
    from cli.settings import add_commands as add_settings_commands
    from cli.train import add_commands

    add_commands(commands)
    add_render_commands(commands)
    add_service_commands(commands)
    add_settings_commands(commands)
    add_bench_commands(commands)
    add_load_commands(commands)
    add_scale_commands(commands)
    add_memory_commands(commands)
    add_step_commands(commands)
    add_render_bench_commands(commands)
    add_results_commands(commands)
    return parser


# What the command line returns for each kind of error (model/errors.py); a traceback means a bug.
EXIT_CODES = {"invalid": 2, "conflict": 2, "busy": 3, "unavailable": 3, "failed": 2}


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from pydantic import ValidationError

    from model.errors import LecoError

    try:
        return args.func(args)
    except ValidationError as exc:  # a job config the schema refuses: name each field
        problems = "; ".join(
            f"{'.'.join(map(str, e['loc'])) or 'config'}: {e['msg']}" for e in exc.errors()
        )
        print(f"leco: error: invalid job config: {problems}", file=sys.stderr)
        return 2
    except LecoError as exc:
        print(f"leco: error: {exc}", file=sys.stderr)
        return EXIT_CODES[exc.kind]
    except (FileExistsError, FileNotFoundError, ValueError) as exc:  # a path or value given
        print(f"leco: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

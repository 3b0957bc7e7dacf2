"""`leco results`: render docs/RESULTS.md and README.md's results block from docs/results/*.json,
check that they are current (`--check`), or add a standing from a benchmark's folder (`add`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def results_command(args: argparse.Namespace) -> int:
    from bench import results

    root = Path(args.root) if args.root else results.ROOT
    if args.action == "add":
        out = results.add(
            Path(args.bench_dir),
            root,
            args.name,
            args.recipe,
            family=args.family,
            scene=args.scene,
            commit=args.commit,
            headline=args.headline,
            note=args.note,
        )
        print(out)
        return 0
    if args.check:
        stale = results.stale(root)
        for path in stale:
            print(
                f"leco results: {path} is not what docs/results/*.json render: run `leco results`",
                file=sys.stderr,
            )
        return 1 if stale else 0
    for path in results.write(root):
        print(path)
    return 0


def add_commands(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "results",
        help="render docs/RESULTS.md and README's results block from docs/results/*.json "
        "(--check: fail when they are stale; add: a standing from a benchmark's folder)",
    )
    parser.add_argument(
        "--check",
        action="store_true",
        help="exit 1, naming the file, when a rendered file is not what the summaries render",
    )
    parser.add_argument(
        "--root", default=None, help="the repository to work in (default: this checkout)"
    )
    parser.set_defaults(func=results_command, action=None)
    actions = parser.add_subparsers(dest="action")
    add = actions.add_parser(
        "add",
        help="compact a `leco bench` folder's results.json into docs/results/NAME.json, replacing "
        "the old summary of that name",
    )
    add.add_argument("bench_dir", metavar="BENCH_OUT_DIR", help="the folder `leco bench` wrote")
    add.add_argument("--name", required=True, help="the summary's name, e.g. switch-nerf-city-0")
    add.add_argument(
        "--command",
        dest="recipe",
        metavar="COMMAND",
        required=True,
        help="the committed command that reproduces it, e.g. "
        "'bench/recipes/switch-nerf-city-0.sh OUT'",
    )
    add.add_argument("--family", default=None, help="the family to keep when the bench ran several")
    add.add_argument("--scene", default=None, help="the scene's short name (default: its folder's)")
    add.add_argument("--commit", default=None, help="the commit measured (default: HEAD)")
    add.add_argument("--headline", action="store_true", help="the family's table in README.md")
    add.add_argument("--note", default="", help="a short note printed under the table")
    add.add_argument("--root", default=argparse.SUPPRESS, help="as for `leco results`")

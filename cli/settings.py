"""`leco settings`: every profile setting a job can override, with its value and meaning."""

from __future__ import annotations

import argparse
import json


def settings_command(args: argparse.Namespace) -> int:
    from model.profiles import get_profile, settings

    rows = [r for r in settings(get_profile(args.profile)) if r[0].startswith(args.prefix)]
    if not rows:
        raise ValueError(f"no setting starts with {args.prefix!r}: try `leco settings` alone")
    if args.json:
        print(json.dumps([{"key": k, "value": v, "description": d} for k, v, d in rows], indent=2))
        return 0
    width = max(len(k) for k, _, _ in rows)
    for key, value, description in rows:
        print(f"{key:<{width}}  {json.dumps(value)}\n{'':<{width}}  {description}")
    return 0


def add_commands(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "settings",
        help="list the profile settings `--set KEY=VALUE` and a job's overrides take",
    )
    parser.add_argument(
        "prefix", nargs="?", default="", help="only keys starting with this, e.g. guided."
    )
    parser.add_argument("--profile", default="cpu", help="paper | cpu | smoke (default: cpu)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")
    parser.set_defaults(func=settings_command)

"""`leco scene poses PHOTOS --out DIR`: poses for a folder of photos (workers/poses), with a
progress bar per stage. Every setting of the poses schema is a flag of its own."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, TextIO

from workers.poses.settings import PosesConfig

BAR = 28


class Progress:
    """One line a stage: redrawn in place on a terminal, a line per quarter elsewhere (logs)."""

    def __init__(self, stream: TextIO):
        self.stream = stream
        self.tty = stream.isatty()
        self.label = ""
        self.shown = -1
        self.open = False

    def _end_line(self) -> None:
        if self.open:
            self.stream.write("\n")
            self.open = False

    def __call__(self, event: dict) -> None:
        kind = event["event"]
        if kind == "stage":
            self._end_line()
            self.label = f"[{event['index'] + 1}/{event['stages']} {event['stage']}]"
            self.shown = -1
        elif kind == "progress":
            self._bar(event)
        else:  # log, warning
            self._end_line()
            prefix = "warning: " if kind == "warning" else ""
            self.stream.write(f"{self.label or '[poses]'} {prefix}{event['message']}\n")
        self.stream.flush()

    def _bar(self, event: dict) -> None:
        done, total = event["done"], max(event["total"], 1)
        share = min(done / total, 1.0)
        text = f"{self.label} {share:4.0%} ({done:,}/{event['total']:,} {event['unit']})"
        if self.tty:
            filled = int(round(share * BAR))
            bar = f"[{'#' * filled}{'.' * (BAR - filled)}]"
            self.stream.write(f"\r{self.label} {bar} {text[len(self.label) + 1 :]}")
            self.open = share < 1.0
            if not self.open:
                self.stream.write("\n")
        elif int(share * 4) > self.shown:
            self.shown = int(share * 4)
            self.stream.write(text + "\n")


def add_poses_command(scene: Any) -> None:
    poses = scene.add_parser(
        "poses",
        help="find camera poses for a folder of photos (COLMAP by pycolmap) and write a COLMAP "
        "scene folder any command here reads",
    )
    poses.add_argument("photos", help="folder of photos (.jpg, .png, .tif; subfolders too)")
    poses.add_argument("--out", required=True, help="the scene folder to write (new or empty)")
    poses.add_argument("--json", action="store_true", help="print the summary as JSON")
    for name, field in PosesConfig.model_fields.items():
        poses.add_argument(
            f"--{name.replace('_', '-')}",
            dest=f"setting_{name}",
            default=None,
            metavar=name.upper(),
            help=f"{field.description} (default: {field.default})",
        )
    poses.set_defaults(func=poses_command)


def settings_of(args: argparse.Namespace) -> PosesConfig:
    given = {
        name: getattr(args, f"setting_{name}")
        for name in PosesConfig.model_fields
        if getattr(args, f"setting_{name}") is not None
    }
    # flags arrive as text: numbers are JSON-decoded, words kept as strings; the schema decides
    values = {}
    for name, text in given.items():
        try:
            values[name] = json.loads(text)
        except json.JSONDecodeError:
            values[name] = text
    return PosesConfig.model_validate(values)


def poses_command(args: argparse.Namespace) -> int:
    from workers.poses.process import run_poses

    config = settings_of(args)
    summary = run_poses(Path(args.photos), Path(args.out), config, Progress(sys.stderr))
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        geo = summary["georeference"]
        seconds = summary["seconds"]
        print(
            f"{args.out}: {summary['registered']} of {summary['photos']} photos posed, "
            f"{summary['cameras']} camera(s), {summary['points']:,} points, reprojection error "
            f"{summary['mean_reprojection_error_px']} px; "
            + (
                f"east-north-up metres from the GPS of {geo['photos_with_gps']} photos "
                f"(median error {geo['gps_error_m']['median']:.2f} m)"
                if geo
                else "the cameras' own frame and scale (no GPS)"
            )
        )
        print("seconds: " + ", ".join(f"{k} {v:g}" for k, v in seconds.items()))
    return 0

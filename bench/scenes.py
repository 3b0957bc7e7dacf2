"""The benchmark scenes by short name: where each lives, and how the generated ones are built.

    city-N, village-N, tiny-N   a synthetic scene of that preset and seed (`leco scene synth`),
                                generated under $LECO_SCENES (default scenes/) the first time it
                                is asked for
    lego, fern                  the NeRF datasets, at $LEGO and $FERN (default
                                ../shared/datasets/...; docs/SCENES.md says where to get them)
    rooftop                     $LECO_SCENES/giza-rooftop, built from $ROOFTOP_MIRROR, a
                                fetched mirror of Vincent7140/dataset_perso
                                (bench/real_capture.py; no licence stated: local use)

The suites (bench/suites/) and the recipes (bench/recipes/scenes.sh) name scenes this way;
`python -m bench.scenes NAME` prints a scene's folder, building it first where it is built here.
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

from model.errors import InvalidInput

SYNTHETIC = re.compile(r"^(city|village|tiny)-(\d{1,6})$")
DATASETS = {
    "lego": ("LEGO", "../shared/datasets/nerf_synthetic_lego_200"),
    "fern": ("FERN", "../shared/datasets/nerf_llff_fern"),
}
ROOFTOP = "giza-rooftop"
ROOFTOP_WIDTH = 240
NAMES = "city-N, village-N, tiny-N, lego, fern, rooftop"


class SceneMissing(InvalidInput):
    """A named scene that is not on this machine and cannot be built here."""


def check_name(name: str) -> str:
    """The name, if it is one this module knows; else an error listing the known ones."""
    if SYNTHETIC.match(name) or name in DATASETS or name == "rooftop":
        return name
    raise InvalidInput(f"scene {name!r}: unknown scene name; choose from {NAMES}")


def folder(name: str, root: Path) -> Path:
    """Where the scene lives (it may not exist yet), relative paths taken from `root`."""
    check_name(name)
    if name in DATASETS:
        variable, default = DATASETS[name]
        return (root / os.environ.get(variable, default)).resolve()
    generated = root / os.environ.get("LECO_SCENES", "scenes")
    return generated / (ROOFTOP if name == "rooftop" else name)


def missing_reason(name: str, root: Path) -> str | None:
    """Why the scene can neither be found nor built here, or None if it can be used."""
    where = folder(name, root)
    if where.is_dir() or SYNTHETIC.match(name):
        return None
    if name in DATASETS:
        variable, _ = DATASETS[name]
        return f"scene {name}: {where} is missing (set ${variable}; docs/SCENES.md)"
    if not os.environ.get("ROOFTOP_MIRROR"):
        return (
            f"scene rooftop: {where} is missing and $ROOFTOP_MIRROR is not set (fetch "
            "github:Vincent7140/dataset_perso and point ROOFTOP_MIRROR at its git folder)"
        )
    return None


def resolve(name: str, root: Path, log=lambda text: None) -> Path:
    """The scene's folder, generated or rebuilt first if it is built here and absent."""
    where = folder(name, root)
    if where.is_dir():
        return where
    reason = missing_reason(name, root)
    if reason:
        raise SceneMissing(reason)
    match = SYNTHETIC.match(name)
    if match:
        from model.scenes.synthetic import generate

        log(f"[scenes] generating {name} at {where}")
        generate(match.group(1), int(match.group(2)), where)
    else:
        from bench.real_capture import main as rebuild

        log(f"[scenes] rebuilding the rooftop capture at {where}")
        rebuild(
            [
                "--source",
                os.environ["ROOFTOP_MIRROR"],
                "--out",
                str(where),
                "--width",
                str(ROOFTOP_WIDTH),
            ]
        )
    return where


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print(f"usage: python -m bench.scenes NAME   ({NAMES})", file=sys.stderr)
        return 2
    try:
        print(resolve(args[0], Path.cwd(), log=lambda t: print(t, file=sys.stderr)))
    except InvalidInput as error:
        print(f"scene: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())

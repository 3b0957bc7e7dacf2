"""A suite's records: one small JSON file per scene and seed holding each method's finished run
(its summary and tracked validation curve, the machine and the day it trained), so a suite too long
for one sitting is finished over several at one commit.

A records folder belongs to one suite and one commit (`source.json`); a run is taken from it only
when it was trained with the spec the suite asks for now (method, seed, profile, budget,
evaluation, `--set`s). Committed under docs/results/suites/, it lets a later checkout continue the
same table: `leco bench --suite NAME --commit C --records DIR`.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from model.errors import InvalidInput

FORMAT = 1


def spec_of(suite, scene, seed: int, method: str, sets: list[str]) -> dict:
    """What a run was asked to be: two runs of one spec at one commit are the same measurement."""
    return {
        "method": method,
        "seed": seed,
        "profile": suite.profile,
        "budget_min": scene.budget_min,
        "eval_every_s": scene.eval_every_s,
        "eval_views": scene.eval_views,
        "sets": list(sets),
    }


def open_records(folder: Path, suite_name: str, commit: str) -> None:
    """Claims FOLDER for this suite and commit, or refuses one that holds another's runs."""
    stamp_file = folder / "source.json"
    if stamp_file.exists():
        stamp = json.loads(stamp_file.read_text())
        if (stamp.get("suite"), stamp.get("commit")) != (suite_name, commit):
            raise InvalidInput(
                f"--records {folder}: holds runs of suite {stamp.get('suite')} at commit "
                f"{str(stamp.get('commit'))[:10]}, not {suite_name} at {commit[:10]}: a records "
                "folder keeps one suite at one commit; name another folder"
            )
        return
    folder.mkdir(parents=True, exist_ok=True)
    write_atomically(stamp_file, {"suite": suite_name, "commit": commit, "format": FORMAT})


def record_path(folder: Path, scene: str, seed: int) -> Path:
    return folder / f"{scene}-seed{seed}.json"


def recorded_runs(folder: Path, scene: str, seed: int) -> list[dict]:
    path = record_path(folder, scene, seed)
    if not path.exists():
        return []
    try:
        return json.loads(path.read_text())["runs"]
    except (json.JSONDecodeError, KeyError, TypeError):
        raise InvalidInput(
            f"{path}: not a suite record (remove it to train its runs again)"
        ) from None


def reusable(runs: list[dict], specs: dict[str, dict]) -> dict[str, dict]:
    """The recorded runs, by method, whose spec is exactly the one asked for."""
    return {r["variant"]: r for r in runs if specs.get(r["variant"]) == r["spec"]}


def condensed(run: dict, spec: dict, machine: dict, command: str, reference: str) -> dict:
    """A finished run as the suite's tables read it: no run folder, no per-step series."""
    return {
        "variant": run["variant"],
        "method": run["method"],
        "label": run["label"],
        "seed": run["seed"],
        "spec": spec,
        "summary": run["summary"],
        "curve": [p for p in run["curve"] if "val_psnr" in p],
        "occupancy_reference": reference,
        "machine": machine,
        "trained_on": time.strftime("%Y-%m-%d"),
        "command": command,
    }


def add_runs(folder: Path, scene: str, seed: int, runs: list[dict]) -> None:
    """The record with RUNS in place of any earlier run of the same methods."""
    new = {r["variant"] for r in runs}
    kept = [r for r in recorded_runs(folder, scene, seed) if r["variant"] not in new]
    payload = {"scene": scene, "seed": seed, "format": FORMAT, "runs": kept + runs}
    write_atomically(record_path(folder, scene, seed), payload)


def write_atomically(path: Path, payload: dict) -> None:
    """A record is whole or absent: an interrupted write leaves the previous one."""
    partial = path.with_name(f".{path.name}.partial-{os.getpid()}")
    partial.write_text(json.dumps(payload, indent=1))
    partial.replace(path)

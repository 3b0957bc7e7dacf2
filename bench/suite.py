"""Suites: named sets of scenes, each with its budget, and the seeds and methods to train on them,
run as one command from a frozen copy of the code and reported as one table per scene and the mean
over scenes per method.

`dev` holds the scenes settings are chosen on, `held-out` the scenes a default must not get worse
on (docs/BENCHMARKS.md, "Choosing a default"). A suite's folder holds the frozen source
(`source/`, one commit for every run), one `leco bench` folder per scene and seed
(`scenes/NAME/seedK/`, whose finished runs are reused when the command is run again), the records
the tables are read from (`records/`, or a folder named with `--records` that a later checkout can
continue: bench/suite_records.py), `suite.json` and `report.md`.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
import tomllib
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from bench.analysis import get, mean_std
from bench.scenes import check_name, missing_reason, resolve
from bench.suite_records import (
    add_runs,
    condensed,
    open_records,
    recorded_runs,
    reusable,
    spec_of,
)
from model.errors import Failed, InvalidInput

ROOT = Path(__file__).resolve().parents[1]  # the checkout this module belongs to
SUITES = ROOT / "bench" / "suites"
# a run whose last tracked validation PSNR is within this of its best ended at its best
END_TOLERANCE_DB = 0.05


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class SuiteScene(Strict):
    name: str = Field(description="a scene's short name (bench/scenes.py)")
    budget_min: float | None = Field(
        default=None, gt=0, le=600, description="training minutes per run; null: the step counts"
    )
    eval_every_s: float | None = Field(default=None, gt=0, description="default: budget/15")
    eval_views: int = Field(default=4, ge=1, le=64)

    @field_validator("name")
    @classmethod
    def known(cls, name: str) -> str:
        return check_name(name)


class Suite(Strict):
    name: str = Field(pattern=r"^[a-z0-9][a-z0-9-]*$")
    description: str = ""
    profile: str = "cpu"
    seeds: list[int] = Field(min_length=1)
    methods: list[str] = Field(min_length=1)
    scenes: list[SuiteScene] = Field(min_length=1)

    @field_validator("seeds")
    @classmethod
    def non_negative(cls, seeds: list[int]) -> list[int]:
        if any(s < 0 for s in seeds):
            raise ValueError("seeds are non-negative")
        return seeds

    @field_validator("methods")
    @classmethod
    def selectable(cls, methods: list[str]) -> list[str]:
        from bench.variants import select

        select(methods, ablation=False)  # raises naming the unknown ones
        return methods

    @field_validator("scenes")
    @classmethod
    def unique(cls, scenes: list[SuiteScene]) -> list[SuiteScene]:
        names = [s.name for s in scenes]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ValueError(f"scene(s) named twice: {', '.join(twice)}")
        return scenes


def available() -> list[str]:
    return sorted(p.stem for p in SUITES.glob("*.toml"))


def load_suite(name: str) -> Suite:
    """A committed suite by name (bench/suites/NAME.toml), or a suite file by path."""
    path = Path(name) if name.endswith(".toml") or "/" in name else SUITES / f"{name}.toml"
    if not path.is_file():
        raise InvalidInput(
            f"--suite {name}: no such suite (committed: {', '.join(available())}; or a .toml path)"
        )
    try:
        data = tomllib.loads(path.read_text())
        return Suite.model_validate(data)
    except tomllib.TOMLDecodeError as error:
        raise InvalidInput(f"suite {path}: not valid TOML ({error})") from None
    except ValidationError as error:
        problems = "; ".join(
            f"{'.'.join(map(str, e['loc'])) or 'suite'}: {e['msg'].removeprefix('Value error, ')}"
            for e in error.errors()
        )
        raise InvalidInput(f"suite {path}: {problems}") from None


def narrowed(
    suite: Suite, methods: list[str] | None, seeds: list[int] | None, scenes: list[str] | None
) -> Suite:
    """The suite with fewer scenes, or other methods or seeds (a lever's screen runs its own)."""
    if scenes:
        unknown = [s for s in scenes if s not in {x.name for x in suite.scenes}]
        if unknown:
            raise InvalidInput(
                f"--scenes: {', '.join(unknown)} not in suite {suite.name} "
                f"({', '.join(s.name for s in suite.scenes)})"
            )
    data = suite.model_dump()
    data["methods"] = methods if methods is not None else suite.methods
    data["seeds"] = seeds if seeds is not None else suite.seeds
    data["scenes"] = [s for s in data["scenes"] if not scenes or s["name"] in scenes]
    try:
        return Suite.model_validate(data)
    except ValidationError as error:
        raise InvalidInput(
            "; ".join(f"--{e['loc'][0]}: {e['msg']}" for e in error.errors())
        ) from None


def git(root: Path, *args: str) -> str:
    done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise Failed(f"git {' '.join(args)} in {root}: {done.stderr.strip()}")
    return done.stdout.strip()


def freeze(out: Path, root: Path, log, rev: str = "HEAD") -> dict:
    """The committed code (REV, HEAD unless named) copied to OUT/source once, so every run of the
    suite trains the same code while the checkout changes. A folder frozen at another commit is
    refused."""
    commit = git(root, "rev-parse", "--verify", f"{rev}^{{commit}}")
    dirty = rev == "HEAD" and bool(git(root, "status", "--porcelain", "--untracked-files=no"))
    stamp_file, source = out / "source.json", out / "source"
    if stamp_file.exists():
        stamp = json.loads(stamp_file.read_text())
        if stamp["commit"] != commit:
            raise InvalidInput(
                f"{out} holds runs of commit {stamp['commit'][:10]}, not {commit[:10]}: a "
                "suite's runs come from one commit; choose another --out"
            )
        return stamp
    if dirty:
        log("[suite] uncommitted changes are not measured: the suite runs HEAD as committed")
    out.mkdir(parents=True, exist_ok=True)
    partial = out / f".source.partial-{os.getpid()}"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir()
    try:
        archive = subprocess.run(["git", "-C", str(root), "archive", commit], capture_output=True)
        if archive.returncode != 0:
            raise Failed(f"git archive {commit}: {archive.stderr.decode(errors='replace').strip()}")
        tar = subprocess.run(["tar", "-x", "-C", str(partial)], input=archive.stdout)
        if tar.returncode != 0:
            raise Failed(f"unpacking commit {commit[:10]} into {partial} failed")
        shutil.rmtree(source, ignore_errors=True)
        partial.rename(source)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    stamp = {"commit": commit, "dirty_checkout": dirty, "frozen_at": time.strftime("%Y-%m-%d")}
    stamp_file.write_text(json.dumps(stamp, indent=1))
    return stamp


def scene_command(
    suite: Suite,
    scene: SuiteScene,
    folder: Path,
    out: Path,
    sets: list[str],
    methods: list[str],
    seed: int,
) -> list[str]:
    """The `leco bench` command training METHODS at SEED on one scene (from the frozen source)."""
    words = ["bench", "--scene", str(folder), "--profile", suite.profile, "--out", str(out)]
    words += ["--methods", ",".join(methods), "--seeds", str(seed)]
    words += ["--eval-views", str(scene.eval_views)]
    if scene.budget_min is not None:
        words += ["--budget-min", f"{scene.budget_min:g}"]
    if scene.eval_every_s is not None:
        words += ["--eval-every-s", f"{scene.eval_every_s:g}"]
    for item in sets:
        words += ["--set", item]
    return words


def run_suite(
    suite: Suite,
    out: Path,
    sets: list[str],
    command: str,
    log,
    root: Path = ROOT,
    rev: str = "HEAD",
    records: Path | None = None,
):
    """Every scene and seed of the suite in turn from a frozen copy of REV, each (scene, seed)'s
    finished runs kept in the records folder (OUT/records unless named), then suite.json and
    report.md from the records. Scenes that cannot be found or built are named before anything
    trains; runs the records already hold are not trained again."""
    missing = [r for r in (missing_reason(s.name, root) for s in suite.scenes) if r]
    if missing:
        raise InvalidInput("; ".join(missing))
    # The scenes train from the frozen copy; the tables are written by this process after hours in
    # which the checkout may change: their code is imported now, as committed when the suite began.
    from bench.report import machine
    from bench.suite_report import write_report

    stamp = freeze(out, root, log, rev)
    records = records or out / "records"
    open_records(records, suite.name, stamp["commit"])
    source = out / "source"
    env = {**os.environ, "PYTHONPATH": str(source)}
    for scene in suite.scenes:
        folder = resolve(scene.name, root, log).resolve()
        for seed in suite.seeds:
            specs = {m: spec_of(suite, scene, seed, m, sets) for m in suite.methods}
            have = reusable(recorded_runs(records, scene.name, seed), specs)
            todo = [m for m in suite.methods if m not in have]
            if not todo:
                log(f"[suite] {scene.name} seed {seed}: every run is in {records}")
                continue
            bench_out = (out / "scenes" / scene.name / f"seed{seed}").resolve()
            words = scene_command(suite, scene, folder, bench_out, sets, todo, seed)
            log(f"[suite] {scene.name} seed {seed}: leco {' '.join(words)}")
            done = subprocess.run([sys.executable, "-m", "cli.main", *words], cwd=source, env=env)
            if done.returncode != 0:
                raise Failed(
                    f"scene {scene.name} seed {seed}: leco bench exited {done.returncode}; its "
                    "finished runs are kept and the same command continues from them"
                )
            results = json.loads((bench_out / "results.json").read_text())
            line = "leco " + " ".join(words)
            runs = [
                condensed(r, specs[r["variant"]], machine(), line, results["occupancy_reference"])
                for r in results["runs"]
                if r["variant"] in specs
            ]
            add_runs(records, scene.name, seed, runs)
    summary = aggregate(suite, records, stamp, command, sets)
    (out / "suite.json").write_text(json.dumps(summary, indent=1))
    write_report(summary, out / "report.md")
    return summary


def run_row(runs: list[dict]) -> dict:
    """One method's numbers on one scene: means over its seeds, and each seed's PSNR."""

    def mean(path: str):
        return mean_std([get(r["summary"], path) for r in runs])[0]

    layers = [get(r["summary"], "occupancy.layers") or [] for r in runs]
    lowest = [min(x["recall"] for x in ls if x.get("recall") is not None) for ls in layers if ls]
    ends = []
    for r in runs:
        tracked = [p for p in r["curve"] if p.get("phase") == "main" and "val_psnr" in p]
        if tracked:
            best = max(tracked, key=lambda p: p["val_psnr"])
            ends.append(
                {
                    "seed": r["seed"],
                    "best_psnr": best["val_psnr"],
                    "best_at_min": best["wall_time_s"] / 60,
                    "last_psnr": tracked[-1]["val_psnr"],
                    "ends_at_best": tracked[-1]["val_psnr"] >= best["val_psnr"] - END_TOLERANCE_DB,
                }
            )
    return {
        "label": runs[0]["label"],
        "method": runs[0]["method"],
        "seeds": [r["seed"] for r in runs],
        "psnr": mean("val.psnr"),
        "psnr_by_seed": [get(r["summary"], "val.psnr") for r in runs],
        "ssim": mean("val.ssim"),
        "lpips_vgg": mean("val.lpips_vgg"),
        "occupancy_f1": mean("occupancy.f1"),
        "occupancy_recall": mean("occupancy.recall"),
        "lowest_layer_recall": min(lowest) if lowest else None,
        "steps": mean("steps.total"),
        "tracked": ends,
    }


def aggregate(suite: Suite, records: Path, stamp: dict, command: str, sets: list[str]) -> dict:
    """suite.json: per scene, a row per method; and per method, the mean over the scenes."""
    scenes: dict[str, dict[str, Any]] = {}
    machines: dict[str, bool] = {}
    for scene in suite.scenes:
        by_variant: dict[str, list[dict]] = {}
        for seed in suite.seeds:
            specs = {m: spec_of(suite, scene, seed, m, sets) for m in suite.methods}
            have = reusable(recorded_runs(records, scene.name, seed), specs)
            for name in suite.methods:
                by_variant.setdefault(name, []).append(have[name])
        runs = [r for rs in by_variant.values() for r in rs]
        for r in runs:
            machines[machine_line(r["machine"])] = True
        scenes[scene.name] = {
            "budget_min": scene.budget_min,
            "occupancy_reference": "; ".join(dict.fromkeys(r["occupancy_reference"] for r in runs)),
            "commands": list(dict.fromkeys(r["command"] for r in runs)),
            "trained_on": sorted(
                {f"{r['trained_on']}, {machine_line(r['machine'])}" for r in runs}
            ),
            "rows": {name: run_row(rs) for name, rs in by_variant.items()},
        }
    methods = {}
    for name in suite.methods:
        psnrs = [s["rows"][name]["psnr"] for s in scenes.values()]
        ranks = [rank_of(s["rows"], name) for s in scenes.values()]
        methods[name] = {
            "label": next(s["rows"][name]["label"] for s in scenes.values()),
            "mean_psnr": mean_std(psnrs)[0] if None not in psnrs else None,
            "scenes": len(psnrs),
            "mean_rank": mean_std([r for r in ranks if r is not None])[0],
            "best_on": [n for n, s in scenes.items() if rank_of(s["rows"], name) == 1],
        }
    return {
        "suite": suite.model_dump(),
        "commit": stamp["commit"],
        "dirty_checkout": stamp["dirty_checkout"],
        "command": command,
        "records": str(records),
        "machines": list(machines),
        "finished_at": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "scenes": scenes,
        "methods": methods,
    }


def machine_line(m: dict) -> str:
    gpu = f", {m['gpu']}" if m.get("gpu") else ""
    return f"{m['cpu']}, {m['cores']} cores{gpu}; torch {m['torch']}"


def rank_of(rows: dict, name: str) -> int | None:
    """1 for the best PSNR on the scene among the rows that have one."""
    psnr = rows[name]["psnr"]
    if psnr is None:
        return None
    return 1 + sum(1 for r in rows.values() if r["psnr"] is not None and r["psnr"] > psnr)

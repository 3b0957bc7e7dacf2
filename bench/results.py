"""Today's standings: one compact summary per benchmark that holds (docs/results/*.json: plan,
machine, stamp, one row per run, no curves), rendered into docs/RESULTS.md and README.md's results
block by `leco results`. `leco results --check` fails when the docs are not what the summaries
render, so they cannot go stale; `leco results add` compacts what `leco bench` wrote into a summary,
replacing the old one when a default changes (a standing is replaced, not appended)."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from model.errors import InvalidInput
from model.methods import METHODS

ROOT = Path(__file__).resolve().parents[1]  # the checkout this module belongs to
SUMMARIES = Path("docs/results")
RESULTS_MD = Path("docs/RESULTS.md")
README = Path("README.md")
BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"
NAME = re.compile(r"^[a-z0-9][a-z0-9-]*$")


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Plan(Strict):
    """What was trained: the scene as the command named it, the profile and what it overrode."""

    scene: str
    profile: str
    budget_min: float | None = Field(default=None, gt=0)
    seeds: list[int] = Field(min_length=1)
    methods: list[str] = Field(min_length=1)
    overrides: dict[str, Any] = Field(default_factory=dict)
    gpu: bool = False

    @field_validator("seeds")
    @classmethod
    def non_negative(cls, seeds: list[int]) -> list[int]:
        if any(s < 0 for s in seeds):
            raise ValueError("seeds are non-negative")
        return seeds

    @field_validator("methods")
    @classmethod
    def registered(cls, methods: list[str]) -> list[str]:
        return [registered_method(m) for m in methods]


class Machine(Strict):
    cpu: str | None = None
    cores: int | None = Field(default=None, ge=1)
    gpu: str | None = None
    torch: str | None = None
    python: str | None = None


class Stamp(Strict):
    date: str = Field(pattern=r"^\d{4}-\d{2}-\d{2}$")
    # the repository at this commit holds the code that was measured
    commit: str = Field(pattern=r"^[0-9a-f]{7,40}(-dirty)?$")
    # the committed command that reproduces the table (a script under bench/recipes/)
    recipe: str = Field(min_length=1)
    command: str | None = None  # the benchmark's own command line, as it ran


class Row(Strict):
    """One run (`seed`), or the mean over the plan's seeds (`seed` null). Empty: not measured."""

    method: str
    label: str
    seed: int | None = Field(default=None, ge=0)
    psnr: float | None = None
    psnr_std: float | None = Field(default=None, ge=0)
    ssim: float | None = None
    lpips_vgg: float | None = None
    steps: int | None = Field(default=None, ge=0)  # main-phase steps
    phase1_steps: int | None = Field(default=None, ge=0)
    rays_per_s: float | None = Field(default=None, gt=0)
    samples_per_ray: float | None = Field(default=None, ge=0)  # main-network samples
    samples_per_hit_ray: float | None = Field(default=None, ge=0)
    # training seconds until the tracked views first reach the reference's best ("never": not
    # within the budget)
    time_to_reference_best_s: float | Literal["never"] | None = None
    occupancy_f1: float | None = Field(default=None, ge=0, le=1)
    note: str | None = None

    @field_validator("method")
    @classmethod
    def registered(cls, method: str) -> str:
        return registered_method(method)


class Summary(Strict):
    family: str  # the registry's family of the rows' main network
    scene: str  # the scene's short name in the docs
    headline: bool = False  # the family's table in README.md
    reference: str | None = None  # the method whose best PSNR the time column is measured to
    plan: Plan
    machine: Machine
    stamp: Stamp
    rows: list[Row] = Field(min_length=1)
    note: str = ""

    @field_validator("family")
    @classmethod
    def known_family(cls, family: str) -> str:
        known = list(dict.fromkeys(m.family for m in METHODS.values()))
        if family not in known:
            raise ValueError(f"unknown family {family!r}: choose one of {', '.join(known)}")
        return family


def registered_method(name: str) -> str:
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}: choose one of {', '.join(METHODS)}")
    return name


# Loading


def load(path: Path) -> Summary:
    """One summary, validated; a bad one is refused naming the file and the field."""
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise InvalidInput(f"{path}: not a readable JSON summary ({error})") from None
    try:
        return Summary.model_validate(data)
    except ValidationError as error:
        problems = "; ".join(
            f"{'.'.join(map(str, e['loc'])) or 'summary'}: {e['msg'].removeprefix('Value error, ')}"
            for e in error.errors()
        )
        raise InvalidInput(f"{path}: {problems}") from None


def load_all(root: Path) -> list[tuple[Path, Summary]]:
    paths = sorted((root / SUMMARIES).glob("*.json"))
    if not paths:
        raise InvalidInput(f"{root / SUMMARIES}: no summaries (*.json) to render")
    return [(p, load(p)) for p in paths]


# Rendering

NOISE = """## How to read these numbers

- **One seed is not a result.** Three runs of seed 0 spanned 2.6 dB (NGP+LeCO on city-0 at 8
  minutes, 2026-11-27; two of them the very same command, 0.86 dB apart), and reruns of a fixed
  seed moved by about 0.5 dB elsewhere. A difference under about 0.3 dB needs a second seed before
  it means anything.
- **Compare rows of one table only.** A table's runs ran one after another on one machine, most in
  one command (pairs interleaved by seed; the note says where not), so the machine's drift falls on
  all of them. Its speed varied by up to 2.6x between tables: rows of different tables do not
  compare.
- **Compare ratios within one run.** Rays/s and the time to the reference's best are read as ratios
  between rows of the same table, never as absolute numbers across tables.
- **What the columns are.** Times are training compute (validation and checkpoints excluded; LeCO's
  include its occupancy phase, phase 1). PSNR, SSIM and LPIPS are the final evaluation on every
  validation view under Mega-NeRF's protocol (docs/TRAINING.md). Steps are main-phase steps, with
  phase 1's in brackets. "To X's best" is when a run's curve on the tracked validation views first
  reaches the best PSNR the reference X reached there ("never": not within the budget). Samples are
  the main network's, per ray or per ray that crosses the scene's box (hit ray). An empty cell was
  not measured; "± s" is the standard deviation over seeds."""

INTRO = """# Results

<!-- Generated by `leco results` from docs/results/*.json; edit those, not this file. -->

Today's standings: for each family and scene, the most recent benchmark run with the defaults the
code has now. Each table stands under its stamp (date, commit, machine, seeds, budget) and the
committed recipe that reproduces it. A family and scene missing here has no measurement with
today's defaults; its last numbers, and every lever tried, are in [EXPERIMENTS.md](EXPERIMENTS.md).
[BENCHMARKS.md](BENCHMARKS.md) says how to run a benchmark and how to add or replace a standing."""


def cell(value: float | None, spec: str) -> str:
    return "" if value is None else format(value, spec)


def psnr_cell(row: Row) -> str:
    text = cell(row.psnr, ".2f")
    return f"{text} ± {row.psnr_std:.2f}" if text and row.psnr_std is not None else text


def steps_cell(row: Row) -> str:
    text = cell(row.steps, ",")
    if row.phase1_steps is None:
        return text
    return f"{text} (+ {row.phase1_steps:,})"


def time_cell(row: Row) -> str:
    t = row.time_to_reference_best_s
    return "never" if t == "never" else cell(t, ",.0f") + (" s" if t is not None else "")


def columns(summary: Summary) -> list[tuple[str, Any]]:
    """(header, row -> cell) of every column; the renderer drops a column no row has."""
    ref = summary.reference
    to_ref = f"to {METHODS[ref].label}'s best" if ref in METHODS else "to the reference's best"
    return [
        ("method", lambda r: r.label),
        ("seed", lambda r: "mean" if r.seed is None else str(r.seed)),
        ("PSNR", psnr_cell),
        ("SSIM", lambda r: cell(r.ssim, ".3f")),
        ("LPIPS (VGG)", lambda r: cell(r.lpips_vgg, ".3f")),
        ("steps (+ phase 1)", steps_cell),
        ("rays/s (main)", lambda r: cell(r.rays_per_s, ",.0f")),
        ("samples / ray", lambda r: cell(r.samples_per_ray, ".1f")),
        ("samples / hit ray", lambda r: cell(r.samples_per_hit_ray, ".1f")),
        (to_ref, time_cell),
        ("occupancy F1", lambda r: cell(r.occupancy_f1, ".3f")),
    ]


def table(summary: Summary, rows: list[Row]) -> str:
    cols = columns(summary)
    cells = [[get(r) for _, get in cols] for r in rows]
    keep = [i for i, (header, _) in enumerate(cols) if i < 2 or any(c[i] for c in cells)]
    lines = ["| " + " | ".join(cols[i][0] for i in keep) + " |", "|" + "---|" * len(keep)]
    lines += ["| " + " | ".join(c[i] for i in keep) + " |" for c in cells]
    return "\n".join(lines)


def machine_text(m: Machine) -> str:
    host = (m.cpu or "host CPU not recorded") + (f", {m.cores} cores" if m.cores else "")
    parts = [f"one {m.gpu} ({host})" if m.gpu else f"{host}, no GPU"]
    parts += [f"torch {m.torch}"] if m.torch else []
    parts += [f"Python {m.python}"] if m.python else []
    return ", ".join(parts)


def stamp_text(summary: Summary, short: bool = False) -> str:
    s, p = summary.stamp, summary.plan
    budget = f"{p.budget_min:g} min per method" if p.budget_min else "the profile's step counts"
    seeds = ", ".join(map(str, p.seeds))
    sets = "".join(f" `--set {k}={json.dumps(v)}`" for k, v in p.overrides.items())
    lines = [
        f"Measured {s.date} at commit `{s.commit}` on {machine_text(summary.machine)}; "
        f"`{p.profile}` profile{sets}, {budget}, seed{'s' if len(p.seeds) > 1 else ''} {seeds}.",
        f"Reproduce: `{s.recipe}`.",
    ]
    if s.command and not short:
        lines.append(f"Ran as: `{s.command}`.")
    return "  \n".join(lines)


def block(summary: Summary, short: bool = False) -> str:
    """The stamp, the table and its notes. Short (README.md): the means alone where there are
    several seeds, and neither the command as it ran nor a note but the rows'."""
    rows = summary.rows
    if short and any(r.seed is None for r in rows):
        rows = [r for r in rows if r.seed is None]
    parts = [stamp_text(summary, short), "", table(summary, rows)]
    notes = [
        f"- {r.label}, {'all seeds' if r.seed is None else f'seed {r.seed}'}: {r.note}"
        for r in rows
        if r.note
    ]
    if notes:
        parts += [""] + notes
    if summary.note and not short:
        parts += ["", summary.note]
    return "\n".join(parts)


def heading(summary: Summary) -> str:
    return summary.scene + (f" on one {summary.machine.gpu}" if summary.machine.gpu else "")


def ordered(summaries: list[Summary]) -> list[Summary]:
    """Registry family order; in a family the headline first, then CPU before GPU, then by scene,
    and in a scene the tables with the family's "ours" before those without (a peer's)."""
    families = list(dict.fromkeys(m.family for m in METHODS.values()))
    has_ours = lambda s: any(METHODS[r.method].role == "ours" for r in s.rows)
    return sorted(
        summaries,
        key=lambda s: (
            families.index(s.family),
            not s.headline,
            bool(s.machine.gpu),
            s.scene,
            not has_ours(s),
        ),
    )


def render_results(summaries: list[Summary]) -> str:
    parts = [INTRO, "", NOISE]
    family, scene = None, None
    for summary in ordered(summaries):
        if summary.family != family:
            family, scene = summary.family, None
            parts += ["", f"## The {family} family"]
        if heading(summary) != scene:
            scene = heading(summary)
            parts += ["", f"### {scene}"]
        parts += ["", block(summary)]
    return "\n".join(parts) + "\n"


def render_readme_block(summaries: list[Summary]) -> str:
    """One stamped table per family: its headline scene's."""
    parts = [
        "<!-- Generated by `leco results` from docs/results/*.json; edit those, not this block. -->"
    ]
    for summary in ordered([s for s in summaries if s.headline]):
        title = f"**The {summary.family} family, {heading(summary)}**"
        parts += ["", title, "", block(summary, short=True)]
    parts += [
        "",
        "Each seed, the notes, every scene and how to read the noise: "
        "[docs/RESULTS.md](docs/RESULTS.md).",
    ]
    return "\n".join(parts)


def replace_block(text: str, inner: str) -> str | None:
    """README.md with the text between the markers replaced; None when the markers are absent."""
    start, end = text.find(BEGIN), text.find(END)
    if start < 0 or end < start:
        return None
    return text[: start + len(BEGIN)] + "\n" + inner + "\n" + text[end:]


def write(root: Path) -> list[Path]:
    """Renders docs/RESULTS.md and README.md's block (when its markers exist); the files written."""
    summaries = [s for _, s in load_all(root)]
    written = [root / RESULTS_MD]
    replace_file(root / RESULTS_MD, render_results(summaries))
    readme = root / README
    if readme.exists():
        updated = replace_block(readme.read_text(), render_readme_block(summaries))
        if updated is not None:
            replace_file(readme, updated)
            written.append(readme)
    return written


def stale(root: Path) -> list[Path]:
    """The rendered files that are not what the summaries render."""
    summaries = [s for _, s in load_all(root)]
    out = []
    results = root / RESULTS_MD
    if not results.exists() or results.read_text() != render_results(summaries):
        out.append(results)
    readme = root / README
    if readme.exists():
        text = readme.read_text()
        updated = replace_block(text, render_readme_block(summaries))
        if updated is not None and updated != text:
            out.append(readme)
    return out


# Compacting a benchmark's results.json


def add(
    bench_dir: Path,
    root: Path,
    name: str,
    recipe: str,
    *,
    family: str | None = None,
    scene: str | None = None,
    commit: str | None = None,
    headline: bool = False,
    note: str = "",
) -> Path:
    """docs/results/NAME.json from `leco bench`'s BENCH_DIR/results.json, replacing any old one."""
    if not NAME.match(name):
        raise InvalidInput(f"--name {name!r}: lower-case letters, digits and dashes, e.g. city-0")
    source = bench_dir / "results.json"
    try:
        results = json.loads(source.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise InvalidInput(f"{source}: not a benchmark's results.json ({error})") from None
    try:
        summary = compact(
            results,
            recipe=recipe,
            family=family,
            scene=scene,
            commit=commit or current_commit(root),
            headline=headline,
            note=note,
        )
    except (KeyError, TypeError) as error:
        raise InvalidInput(f"{source}: missing or malformed field {error}") from None
    out = root / SUMMARIES / f"{name}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    replace_file(out, json.dumps(summary.model_dump(mode="json"), indent=2) + "\n")
    return out


def replace_file(path: Path, text: str) -> None:
    """Writes beside the file and renames over it: a reader never sees half of it."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    tmp.replace(path)


def compact(
    results: dict,
    *,
    recipe: str,
    commit: str,
    family: str | None = None,
    scene: str | None = None,
    headline: bool = False,
    note: str = "",
) -> Summary:
    """A Summary of one family's compared runs (ablations, ladder rungs and sweep points left out):
    one row per run, and with several seeds a mean row per method."""
    from bench.analysis import main_curve, time_to_psnr
    from model.methods import family_of, with_role

    runs = [r for r in results["runs"] if not (r["ablation"] or r["ladder"] or r["sweep"])]
    families = list(dict.fromkeys(METHODS[r["method"]].family for r in runs))
    if family is None:
        if len(families) != 1:
            raise InvalidInput(
                f"the benchmark ran {len(families)} families ({', '.join(families) or 'none'}): "
                "name one with --family"
            )
        family = families[0]
    members = set(family_of(next((n for n, m in METHODS.items() if m.family == family), None)))
    runs = [r for r in runs if r["method"] in members]
    if not runs:
        raise InvalidInput(f"the benchmark ran no method of the {family} family")
    names = list(dict.fromkeys(r["variant"] for r in runs))
    reference = with_role("reference", names)

    def to_reference_best(run: dict) -> float | Literal["never"] | None:
        ref = [r for r in runs if r["variant"] == reference and r["seed"] == run["seed"]]
        if not ref or not main_curve(ref[0]) or not main_curve(run):
            return None
        target = max(psnr for _, psnr in main_curve(ref[0]))
        t = time_to_psnr(main_curve(run), target)
        return "never" if t is None else round(t, 1)

    rows = [run_row(r, to_reference_best(r)) for r in runs]
    if len({r["seed"] for r in runs}) > 1:
        rows += [
            mean_row([row for row, r in zip(rows, runs) if r["variant"] == variant])
            for variant in names
        ]
    plan = results["plan"]
    machine = results.get("machine") or {}
    return Summary(
        family=family,
        scene=scene or Path(plan["scene"]).name,
        headline=headline,
        reference=reference,
        plan=Plan(
            scene=plan["scene"],
            profile=plan["profile"],
            budget_min=plan.get("budget_min"),
            seeds=plan["seeds"],
            methods=[m for m in plan["methods"] if m in members],
            overrides=plan.get("overrides") or {},
            gpu=bool(plan.get("gpu")),
        ),
        machine=Machine(
            cpu=machine.get("cpu") or "unknown",
            cores=machine.get("cores"),
            gpu=machine.get("gpu"),
            torch=machine.get("torch"),
            python=machine.get("python"),
        ),
        stamp=Stamp(
            date=str(results["finished_at"])[:10],
            commit=commit,
            recipe=recipe,
            command=results.get("command"),
        ),
        rows=rows,
        note=note,
    )


def mean_row(rows: list[Row]) -> Row:
    """A method's mean over its seeds: PSNR with its standard deviation, the ratios alike."""
    from bench.analysis import mean_std

    mean = lambda key: mean_std([getattr(row, key) for row in rows])
    psnr, std = mean("psnr")
    return Row(
        method=rows[0].method,
        label=rows[0].label,
        psnr=rounded(psnr, 4),
        psnr_std=rounded(std, 4),
        ssim=rounded(mean("ssim")[0], 4),
        lpips_vgg=rounded(mean("lpips_vgg")[0], 4),
        samples_per_ray=rounded(mean("samples_per_ray")[0], 2),
        occupancy_f1=rounded(mean("occupancy_f1")[0], 4),
    )


def run_row(run: dict, to_reference_best: float | Literal["never"] | None) -> Row:
    s = run["summary"]
    val = s.get("val") or {}
    phases = (s.get("steps") or {}).get("phases") or {}
    first = [v for k, v in phases.items() if k != "main"]
    return Row(
        method=run["method"],
        label=run["label"],
        seed=run["seed"],
        psnr=rounded(val.get("psnr"), 4),
        ssim=rounded(val.get("ssim"), 4),
        lpips_vgg=rounded(val.get("lpips_vgg"), 4),
        steps=phases.get("main"),
        phase1_steps=sum(first) if first else None,
        rays_per_s=rounded(s.get("rays_per_s"), 0),
        samples_per_ray=rounded(s.get("samples_per_ray"), 2),
        samples_per_hit_ray=rounded((s.get("rays") or {}).get("samples_per_hit_ray"), 2),
        time_to_reference_best_s=to_reference_best,
        occupancy_f1=rounded((s.get("occupancy") or {}).get("f1"), 4),
    )


def rounded(value: Any, digits: int) -> float | None:
    """A finite number rounded for a compact summary; None for anything else (n/a, NaN)."""
    if not isinstance(value, (int, float)) or isinstance(value, bool) or value != value:
        return None
    if value in (float("inf"), float("-inf")):
        return None
    return round(float(value), digits)


def current_commit(root: Path) -> str:
    """The checkout's commit, "-dirty" when tracked files differ from it."""
    git = lambda *args: subprocess.run(
        ["git", *args], cwd=root, capture_output=True, text=True, check=True
    ).stdout.strip()
    try:
        head = git("rev-parse", "--short=7", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.CalledProcessError):
        raise InvalidInput(f"{root}: not a git checkout; give the commit with --commit") from None
    return head + ("-dirty" if dirty else "")


__all__ = ["Summary", "add", "compact", "load", "load_all", "render_results", "stale", "write"]

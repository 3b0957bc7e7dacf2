"""`leco results`: summaries validated, rendered to exact tables, compacted from a benchmark's
folder, checked against the committed docs; and every committed recipe parses and its `leco`
commands are accepted by the command line's own parser."""

import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from bench import results
from cli.main import build_parser, main
from model.errors import InvalidInput

ROOT = Path(__file__).resolve().parents[2]
COMMAND = "leco bench --scene scenes/city-0 --profile cpu --out out --methods leco,switch,ngp"
RECIPES = sorted((ROOT / "bench" / "recipes").iterdir())


def toy(**changes) -> dict:
    summary = {
        "family": "Switch-NeRF",
        "scene": "toy",
        "headline": True,
        "reference": "switch",
        "plan": {
            "scene": "scenes/toy",
            "profile": "cpu",
            "budget_min": 2,
            "seeds": [0, 1],
            "methods": ["leco", "switch"],
        },
        "machine": {"cpu": "Toy CPU", "cores": 2},
        "stamp": {
            "date": "2026-01-02",
            "commit": "abcdef0",
            "recipe": "bench/recipes/toy.sh OUT",
            "command": "leco bench --scene scenes/toy --out OUT",
        },
        "rows": [
            {
                "method": "leco",
                "label": "S+Ours (LeCO)",
                "seed": 0,
                "psnr": 25.123,
                "steps": 9222,
                "phase1_steps": 1329,
                "rays_per_s": 5874.4,
                "time_to_reference_best_s": 232.4,
                "occupancy_f1": 0.5,
                "note": "a note",
            },
            {
                "method": "switch",
                "label": "S-NeRF* (vanilla)",
                "seed": 0,
                "psnr": 24.0,
                "steps": 3796,
                "rays_per_s": 2080,
                "time_to_reference_best_s": "never",
            },
            {"method": "leco", "label": "S+Ours (LeCO)", "psnr": 25.5, "psnr_std": 0.25},
        ],
        "note": "Toy note.",
    }
    summary.update(changes)
    return summary


def write_summary(root: Path, name: str, data: dict) -> Path:
    path = root / "docs" / "results" / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))
    return path


def test_a_toy_summary_renders_to_this_exact_table():
    summary = results.Summary.model_validate(toy())
    assert results.block(summary) == "\n".join(
        [
            "Measured 2026-01-02 at commit `abcdef0` on Toy CPU, 2 cores, no GPU; `cpu` profile, "
            "2 min per method, seeds 0, 1.  ",
            "Reproduce: `bench/recipes/toy.sh OUT`.  ",
            "Ran as: `leco bench --scene scenes/toy --out OUT`.",
            "",
            "| method | seed | PSNR | steps (+ phase 1) | rays/s (main) "
            "| to S-NeRF* (vanilla)'s best | occupancy F1 |",
            "|---|---|---|---|---|---|---|",
            "| S+Ours (LeCO) | 0 | 25.12 | 9,222 (+ 1,329) | 5,874 | 232 s | 0.500 |",
            "| S-NeRF* (vanilla) | 0 | 24.00 | 3,796 | 2,080 | never |  |",
            "| S+Ours (LeCO) | mean | 25.50 ± 0.25 |  |  |  |  |",
            "",
            "- S+Ours (LeCO), seed 0: a note",
            "",
            "Toy note.",
        ]
    )
    page = results.render_results([summary])
    assert "## How to read these numbers" in page
    assert "\n## The Switch-NeRF family\n\n### toy\n\n" + results.block(summary) + "\n" in page
    readme = results.render_readme_block([summary])  # the means alone, the rows' notes only
    short = [
        "**The Switch-NeRF family, toy**",
        "",
        "Measured 2026-01-02 at commit `abcdef0` on Toy CPU, 2 cores, no GPU; `cpu` profile, "
        "2 min per method, seeds 0, 1.  ",
        "Reproduce: `bench/recipes/toy.sh OUT`.",
        "",
        "| method | seed | PSNR |",
        "|---|---|---|",
        "| S+Ours (LeCO) | mean | 25.50 ± 0.25 |",
        "",
        "Each seed, the notes",
    ]
    assert "\n".join(short) in readme


@pytest.mark.parametrize(
    "change, field",
    [
        ({"rows": [{"method": "leco", "label": "x", "psnr": "high"}]}, "rows.0.psnr"),
        ({"rows": [{"method": "nerf-9000", "label": "x"}]}, "rows.0.method"),
        ({"stamp": {"date": "26 Nov", "commit": "abcdef0", "recipe": "r"}}, "stamp.date"),
        ({"family": "Plenoxels"}, "family"),
        (
            {"plan": {"scene": "s", "profile": "cpu", "seeds": [], "methods": ["leco"]}},
            "plan.seeds",
        ),
    ],
)
def test_a_bad_summary_is_refused_naming_the_file_and_the_field(tmp_path, change, field):
    path = write_summary(tmp_path, "bad", toy(**change))
    with pytest.raises(InvalidInput) as refused:
        results.load(path)
    assert str(path) in str(refused.value) and f"{field}:" in str(refused.value)
    assert main(["results", "--root", str(tmp_path)]) == 2  # the command line says so too


def curve(points: list[tuple[float, float]]) -> list[dict]:
    return [
        {"phase": "main", "wall_time_s": t, "val_psnr": p, "step": i}
        for i, (t, p) in enumerate(points)
    ]


def fake_run(method: str, label: str, seed: int, psnr: float, points, phases: dict) -> dict:
    """One entry of results.json's `runs`, as bench/runner.py run_variant returns it."""
    return {
        "variant": method,
        "method": method,
        "label": label,
        "ablation": False,
        "ladder": False,
        "sweep": False,
        "seed": seed,
        "run_dir": f"out/runs/{method}-seed{seed}",
        "summary": {
            "method": method,
            "val": {"psnr": psnr, "ssim": 0.61234, "lpips_vgg": None, "lpips_alex": None},
            "steps": {"total": sum(phases.values()), "phases": phases},
            "rays_per_s": 4321.6,
            "samples_per_ray": 21.04,
            "occupancy": {"f1": 0.45678} if method == "leco" else None,
            "rays": {"samples_per_hit_ray": 22.5},
        },
        "curve": curve(points),
    }


def fake_bench(folder: Path) -> Path:
    """A folder shaped like what `leco bench` writes (bench/cli.py's results, runner.py's runs)."""
    rung = fake_run("leco", "paper's formulation", 0, 20.0, [(60, 19.0)], {"main": 10})
    rung.update(variant="leco-paper", ablation=True, ladder=True)
    other_family = fake_run("ngp", "NGP", 0, 30.0, [(60, 29.0)], {"main": 10})
    runs = [
        fake_run(
            "leco",
            "S+Ours (LeCO)",
            0,
            25.5,
            [(60, 22.0), (120, 24.0)],
            {"occupancy": 900, "main": 5000},
        ),
        fake_run("switch", "S-NeRF* (vanilla)", 0, 24.5, [(60, 21.0), (120, 23.0)], {"main": 3000}),
        fake_run(
            "leco",
            "S+Ours (LeCO)",
            1,
            26.5,
            [(60, 20.0), (120, 22.0)],
            {"occupancy": 950, "main": 5100},
        ),
        fake_run("switch", "S-NeRF* (vanilla)", 1, 25.0, [(60, 23.0), (120, 24.0)], {"main": 3100}),
        rung,
        other_family,
    ]
    data = {
        "plan": {
            "scene": "scenes/city-0",
            "profile": "cpu",
            "budget_min": 2.0,
            "seeds": [0, 1],
            "methods": ["leco", "switch", "ngp", "leco-paper"],
            "eval_every_s": 8.0,
            "eval_views": 4,
            "backend": "local",
            "workers": 1,
            "gpu": False,
            "overrides": {"guided.dilate": 2},
            "downscale": 1,
            "downscale_asked": None,
        },
        "command": COMMAND,
        "machine": {
            "cpu": "Toy CPU",
            "cores": 2,
            "torch": "2.0",
            "python": "3.11.7",
            "os": "Linux",
        },
        "finished_at": "2026-11-29 10:00:00 UTC",
        "bench_wall_s": 600.0,
        "occupancy_reference": "exact ground truth",
        "runs": runs,
        "equal_psnr": [],
        "speedups": {},
        "targets": [],
        "families": [],
        "figures": {},
    }
    folder.mkdir(parents=True)
    (folder / "results.json").write_text(json.dumps(data))
    return folder


def test_add_compacts_a_bench_folder_into_a_summary_and_replaces_the_old_one(tmp_path):
    bench = fake_bench(tmp_path / "bench-out")
    root = tmp_path / "repo"
    old = write_summary(root, "city-0", toy())
    add = ["results", "add", str(bench), "--name", "city-0", "--command", "bench/recipes/x.sh OUT"]
    add += ["--root", str(root), "--commit", "1234567", "--family", "Switch-NeRF"]
    assert main(add) == 0

    summary = results.load(old)  # the same file, replaced
    assert (summary.family, summary.scene, summary.reference) == ("Switch-NeRF", "city-0", "switch")
    assert summary.plan.methods == ["leco", "switch"] and summary.plan.overrides == {
        "guided.dilate": 2
    }
    assert summary.stamp.model_dump() == {
        "date": "2026-11-29",
        "commit": "1234567",
        "recipe": "bench/recipes/x.sh OUT",
        "command": COMMAND,
    }
    runs = [(r.method, r.seed) for r in summary.rows]
    assert runs == [
        ("leco", 0),
        ("switch", 0),
        ("leco", 1),
        ("switch", 1),
        ("leco", None),
        ("switch", None),
    ]
    leco0, switch0, leco1 = summary.rows[:3]
    assert (leco0.psnr, leco0.ssim, leco0.steps, leco0.phase1_steps) == (25.5, 0.6123, 5000, 900)
    assert (leco0.rays_per_s, leco0.samples_per_ray, leco0.samples_per_hit_ray) == (
        4322.0,
        21.04,
        22.5,
    )
    assert (leco0.occupancy_f1, switch0.occupancy_f1, leco0.lpips_vgg) == (0.4568, None, None)
    # vanilla's best on seed 0 is 23.0 (at 120 s), which LeCO's curve crosses at 90 s
    assert (leco0.time_to_reference_best_s, switch0.time_to_reference_best_s) == (90.0, 120.0)
    assert leco1.time_to_reference_best_s == "never"  # vanilla's seed-1 best, 24.0, never reached
    mean = summary.rows[4]
    assert (mean.psnr, mean.psnr_std, mean.occupancy_f1) == (26.0, 0.7071, 0.4568)


def test_add_asks_which_family_when_the_bench_ran_two(tmp_path):
    bench = fake_bench(tmp_path / "bench-out")
    with pytest.raises(InvalidInput, match="--family"):
        results.add(bench, tmp_path, "city-0", "bench/recipes/x.sh OUT", commit="1234567")
    with pytest.raises(InvalidInput, match="--name"):
        results.add(bench, tmp_path, "City 0", "r", family="Switch-NeRF", commit="1234567")


def test_check_fails_on_stale_docs_and_passes_once_rendered(tmp_path, capsys):
    write_summary(tmp_path, "toy", toy())
    outside = "# Readme\n\nKept as it is.\n"
    readme = tmp_path / "README.md"
    readme.write_text(f"{outside}{results.BEGIN}\nold table\n{results.END}\nAfter.\n")
    assert main(["results", "--root", str(tmp_path), "--check"]) == 1
    assert "RESULTS.md" in capsys.readouterr().err

    assert main(["results", "--root", str(tmp_path)]) == 0
    assert main(["results", "--root", str(tmp_path), "--check"]) == 0
    text = readme.read_text()
    assert text.startswith(outside + results.BEGIN) and text.endswith(results.END + "\nAfter.\n")
    assert "old table" not in text and "| S+Ours (LeCO) | mean | 25.50 ± 0.25 |" in text

    results_md = tmp_path / "docs" / "RESULTS.md"
    results_md.write_text(results_md.read_text().replace("25.12", "25.13"))
    readme.write_text(text.replace("25.50", "25.51"))
    capsys.readouterr()
    assert main(["results", "--root", str(tmp_path), "--check"]) == 1
    err = capsys.readouterr().err
    assert str(results_md) in err and str(readme) in err


def test_the_committed_docs_are_what_the_committed_summaries_render():
    assert results.stale(ROOT) == []
    for path, summary in results.load_all(ROOT):
        recipe = summary.stamp.recipe.split()[0]
        assert (ROOT / recipe).is_file(), f"{path.name}: its recipe {recipe} is not committed"


def test_the_results_module_loads_no_pytorch():
    code = "import sys, bench.results, cli.results; sys.exit('torch' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], cwd=ROOT).returncode == 0


# Recipes: each parses, and each `leco` command in it is one the command line accepts.

OPERATOR = re.compile(r"^[;&|<>()]+$")
EXPANSION = re.compile(r"\$\{([^}]*)\}|\$(\w+|@)")


def logical_lines(text: str) -> list[str]:
    lines, current = [], ""
    for line in text.splitlines():
        if line.rstrip().endswith("\\"):
            current += line.rstrip()[:-1] + " "
            continue
        lines.append(current + line)
        current = ""
    return [line for line in lines if line.strip() and not line.lstrip().startswith("#")]


def known_values(lines: list[str]) -> dict[str, str]:
    """Plain assignments (NAME=value without expansions) and each for-loop's first value."""
    values = {}
    for line in lines:
        if m := re.match(r"\s*(\w+)=([^\s$;]+)\s*$", line):
            values[m[1]] = m[2].strip("'\"")
        if m := re.match(r"\s*for (\w+) in (\S+)", line):
            values[m[1]] = m[2].rstrip(";")
    return values


def expand(token: str, values: dict[str, str]) -> str | None:
    """A token with its shell expansions replaced by a known value, a default, or "0" (which every
    argument type accepts); None for a list expansion ("$@", "${a[@]}"), which may be empty."""
    if token in ("$@", "${@}") or re.fullmatch(r"\$\{\w+\[@\]\}", token):
        return None

    def one(m: re.Match) -> str:
        inner = m[1] if m[1] is not None else m[2]
        name, _, default = inner.partition(":-")
        if name in values:
            return values[name]
        return expand(default, values) or "0" if default else "0"

    return EXPANSION.sub(one, token)


def leco_commands(text: str) -> list[list[str]]:
    """The argument lists of every `leco ...`, `.venv/bin/leco ...`, `$leco ...` (a variable holding
    the command) and `python -m cli ...` in a script."""
    lines = logical_lines(text)
    values = known_values(lines)
    found = []
    for line in lines:
        lexer = shlex.shlex(line, posix=True, punctuation_chars=True)
        lexer.whitespace_split = True
        try:
            tokens = list(lexer)
        except ValueError:  # not shell (a heredoc's Python), unless it names the command
            assert not re.search(r"\bleco\b|-m cli\b", line), line
            continue
        for i, token in enumerate(tokens):
            if i and not (OPERATOR.match(tokens[i - 1]) or re.match(r"^\w+=", tokens[i - 1])):
                continue  # not where a command starts (`for m in leco grid`)
            if token in ("leco", "$leco", "${leco}") or token.endswith("/leco"):
                start = i + 1
            elif token.endswith(("python", "python3")) and tokens[i + 1 : i + 3] == ["-m", "cli"]:
                start = i + 3
            else:
                continue
            args = []
            for j, word in enumerate(tokens[start:], start):
                if OPERATOR.match(word):
                    break
                if word.isdigit() and j + 1 < len(tokens) and tokens[j + 1][0] in "<>":
                    break  # a redirection's file descriptor (2>&1)
                value = expand(word, values)
                if value is not None:
                    args.append(value)
            found.append(args)
    return found


@pytest.mark.parametrize("recipe", RECIPES, ids=[p.name for p in RECIPES])
def test_a_recipe_parses_and_the_command_line_accepts_its_leco_commands(recipe):
    checked = subprocess.run(["bash", "-n", str(recipe)], capture_output=True, text=True)
    assert checked.returncode == 0, checked.stderr
    for args in leco_commands(recipe.read_text()):
        try:
            build_parser().parse_args(args)
        except SystemExit:
            pytest.fail(f"{recipe.name}: the command line refuses `leco {shlex.join(args)}`")


def test_the_recipe_reader_finds_every_form_of_the_command():
    script = 'x=1\nleco="python -m cli"\nfor m in leco grid; do\n  $leco train --method "$m" \\\n'
    script += '    --seed "${SEED:-3}" --out "$out" "${sets[@]}" >/dev/null 2>&1\ndone\n'
    script += '.venv/bin/leco bench --scene s --budget-min "$B" --out o | tee log\n'
    script += ".venv/bin/python -m cli settings guided.\n"
    assert leco_commands(script) == [
        ["train", "--method", "leco", "--seed", "3", "--out", "0"],
        ["bench", "--scene", "s", "--budget-min", "0", "--out", "o"],
        ["settings", "guided."],
    ]
    without = {p.name for p in RECIPES if not leco_commands(p.read_text())}
    # gpu-check.sh runs the two; scenes.sh calls bench/scenes.py; graph-breaks.sh step_profile.py
    assert without == {
        "instant-ngp-city-0-h200.sh",
        "switch-nerf-city-0-h200.sh",
        "scenes.sh",
        "graph-breaks.sh",
    }

"""The architecture rule, the CLI surface and the CI contract, checked statically and cheaply."""

import ast
import json
import re
from pathlib import Path

import pytest

from cli.main import main
from tests.helpers import ROOT

FORBIDDEN_IN_MODEL = {
    "service",
    "workers",
    "ray",
    "fastapi",
    "sqlalchemy",
    "uvicorn",
    "httpx",
    "alembic",
    "pydantic_settings",
}


def imported_roots(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    roots = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            roots |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            roots.add(node.module.split(".")[0])
    return roots


def test_model_is_pure_pytorch():
    offenders = {
        str(p.relative_to(ROOT)): sorted(imported_roots(p) & FORBIDDEN_IN_MODEL)
        for p in (ROOT / "model").rglob("*.py")
        if imported_roots(p) & FORBIDDEN_IN_MODEL
    }
    assert offenders == {}


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text().strip().splitlines()[-1].strip()
    readme = (ROOT / "README.md").read_text()
    assert ci == "make test" and re.search(r"^\s*make test\s*$", readme, re.M)


def test_scene_info_text_and_json(lego_dir, capsys):
    assert main(["scene", "info", str(lego_dir)]) == 0
    text = capsys.readouterr().out
    assert "format     blender" in text and "from camera_axes" in text
    assert main(["scene", "info", str(lego_dir), "--json", "--downscale", "4"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["format"] == "blender" and info["cameras"] == 138
    assert info["splits"]["train"]["image_sizes"] == ["50x50"]
    assert info["ground_truth"] == {"depth": False, "occupancy": None}
    rays = info["bounds"]["rays"]
    # a ray in the box travels a share of its diagonal (what a march's samples scale with)
    assert rays["fraction_hitting_foreground"] > 0.99 and 0.2 < rays["mean_diagonal_fraction"] < 1


def test_scene_info_reports_user_errors(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("not a scene")
    assert main(["scene", "info", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("leco: error: ") and "unknown scene format" in err and "notes.txt" in err
    with pytest.raises(SystemExit):
        main(["scene", "synth"])  # --out is required


def test_model_keeps_at_most_six_modules_at_its_top_level():
    # the rest live in folders named for what they do (render, estimators, evaluation, methods, ...)
    top = sorted(p.name for p in (ROOT / "model").glob("*.py") if p.name != "__init__.py")
    assert len(top) <= 6, top


def parameters(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    args = node.args
    names = [a.arg for a in args.posonlyargs + args.args + args.kwonlyargs]
    extra = int(args.vararg is not None) + int(args.kwarg is not None)
    return len([n for n in names if n not in ("self", "cls")]) + extra


def test_no_function_in_model_takes_more_than_fifteen_parameters():
    # a sampler's option flags travel as one options object (estimators/guided.py BinOptions)
    wide = [
        f"{path.relative_to(ROOT)}:{node.name} ({parameters(node)})"
        for path in sorted((ROOT / "model").rglob("*.py"))
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and parameters(node) > 15
    ]
    assert wide == []


def test_a_phase_of_the_training_loop_reads_top_to_bottom():
    tree = ast.parse((ROOT / "workers" / "train" / "loop.py").read_text())
    run_phase = next(
        n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and n.name == "run_phase"
    )
    assert run_phase.end_lineno - run_phase.lineno + 1 < 40


def test_the_tests_mirror_the_tree():
    # every test file sits under the folder of the package it tests, or in architecture/
    folders = {"architecture", "model", "workers", "service", "bench", "cli", "deploy"}
    misplaced = []
    for path in sorted((ROOT / "tests").rglob("test_*.py")):
        parts = path.relative_to(ROOT / "tests").parts[:-1]
        if not parts or parts[0] not in folders:
            misplaced.append(str(path.relative_to(ROOT)))
        elif parts[0] != "architecture" and not (ROOT.joinpath(*parts)).is_dir():
            misplaced.append(str(path.relative_to(ROOT)))
    assert misplaced == []

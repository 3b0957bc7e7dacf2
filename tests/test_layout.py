"""The architecture rule, the CLI surface and the CI contract, checked statically and cheaply."""

import ast
import json
import re
from pathlib import Path

import pytest

from cli.main import main

ROOT = Path(__file__).resolve().parents[1]
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
    assert info["bounds"]["rays"]["fraction_hitting_foreground"] > 0.99


def test_scene_info_reports_user_errors(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("not a scene")
    assert main(["scene", "info", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("leco: error: ") and "unknown scene format" in err and "notes.txt" in err
    with pytest.raises(SystemExit):
        main(["scene", "synth"])  # --out is required

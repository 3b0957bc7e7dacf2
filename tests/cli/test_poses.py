"""`leco scene poses`: a folder of photos to a scene folder from the command line, with a progress
line per stage, and a bad setting or output refused naming it."""

import json

import pytest

from cli.main import main

pytest.importorskip("pycolmap")


@pytest.mark.slow
def test_poses_from_the_command_line(flight, tmp_path, capsys):
    out = tmp_path / "scene"
    code = main(
        ["scene", "poses", str(flight / "photos"), "--out", str(out), "--max-image-size", "320"]
    )
    captured = capsys.readouterr()
    assert code == 0, captured.err
    for stage in ("[1/5 features] 100%", "[2/5 matching] 100%", "[5/5 export]"):
        assert stage in captured.err
    assert "matcher: spatial" in captured.err
    assert "30 of 30 photos posed" in captured.out and "east-north-up metres" in captured.out
    assert main(["scene", "info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["format"] == "colmap" and info["cameras"] == 30


def test_a_bad_setting_is_named(flight, tmp_path, capsys):
    code = main(
        [
            "scene",
            "poses",
            str(flight / "photos"),
            "--out",
            str(tmp_path / "s"),
            "--matcher",
            "nearest",
        ]
    )
    assert code == 2 and "matcher" in capsys.readouterr().err
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("mine")
    code = main(["scene", "poses", str(flight / "photos"), "--out", str(tmp_path / "full")])
    assert code == 2 and "must not exist or be an empty folder" in capsys.readouterr().err

"""`leco bench-memory`: a measured peak RSS beside the API's estimate, for the methods asked."""

import json

from cli.main import main


def test_bench_memory_measures_a_peak_and_sets_it_beside_the_estimate(tiny_scene, tmp_path, capsys):
    out = tmp_path / "memory.json"
    words = ["bench-memory", "--scene", str(tiny_scene.root), "--methods", "leco,switch"]
    words += ["--profile", "smoke", "--rays", "64", "--steps", "2", "--out", str(out)]
    assert main(words) == 0
    rows = json.loads(out.read_text())
    assert [(r["method"], r["rays"]) for r in rows] == [("leco", 64), ("switch", 64)]
    for row in rows:
        # a process with torch and a trained run: hundreds of MiB, within the estimate + 25%
        assert 200 < row["peak_rss_mb"] < 1.25 * row["estimate_mb"]
    assert "2 of 2 within the estimate + 25%" in capsys.readouterr().out

"""Suites (bench/suite.py): the committed files load and name scenes that exist or can be built,
bad files are refused naming what is wrong, a suite's folder keeps one commit, and a suite runs end
to end at the smoke profile from a frozen copy."""

import json
import re
import shutil

import pytest

from bench.scenes import DATASETS, SYNTHETIC, check_name, folder, missing_reason
from bench.suite import Suite, available, freeze, load_suite, narrowed, rank_of
from bench.suite_records import (
    add_runs,
    condensed,
    open_records,
    record_path,
    recorded_runs,
    reusable,
    spec_of,
)
from cli.main import main
from model.errors import Failed, InvalidInput
from model.scenes.synthetic import PRESETS
from tests.helpers import ROOT


def test_the_committed_suites_load_and_name_only_scenes_that_exist_or_can_be_built():
    assert {"dev", "held-out"} <= set(available())
    for name in available():
        suite = load_suite(name)
        assert suite.seeds and suite.methods and suite.scenes
        for scene in suite.scenes:
            match = SYNTHETIC.match(scene.name)
            if match:  # generated here: the preset exists
                assert match.group(1) in PRESETS
            elif scene.name in DATASETS:
                if (ROOT.parent / "shared" / "datasets").is_dir():
                    assert missing_reason(scene.name, ROOT) is None
                    assert folder(scene.name, ROOT).is_dir()
            else:  # the rooftop: built from a fetched mirror, or named as missing
                assert scene.name == "rooftop"
                reason = missing_reason(scene.name, ROOT)
                assert reason is None or "ROOFTOP_MIRROR" in reason


def test_dev_and_held_out_share_no_scene_and_held_out_cities_were_never_measured():
    dev, held = load_suite("dev"), load_suite("held-out")
    assert not {s.name for s in dev.scenes} & {s.name for s in held.scenes}
    assert {s.name for s in dev.scenes} == {"city-0", "lego", "fern", "village-5"}
    # the held-out synthetic scenes appear in no lever's row and no recipe but through the suite:
    # no setting was chosen on them (the ledger's held-out section judges defaults there)
    ledger = (ROOT / "docs" / "EXPERIMENTS.md").read_text()
    start = ledger.index("## Held-out checks")
    end = ledger.index("\n## ", start + 1)
    ledger = ledger[:start] + ledger[end:]
    recipes = "\n".join(p.read_text() for p in (ROOT / "bench" / "recipes").glob("*.sh"))
    for scene in held.scenes:
        if SYNTHETIC.match(scene.name):
            assert not re.search(rf"\b{scene.name}\b", ledger + recipes), scene.name
    assert {s.name.split("-")[0] for s in held.scenes} >= {"city", "village", "rooftop"}
    assert all(s.budget_min for s in dev.scenes + held.scenes)


def write(tmp_path, text):
    path = tmp_path / "suite.toml"
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize(
    "text, message",
    [
        ('name = "x"\nseeds = [0]\nmethods = ["leco"]\n', "scenes: Field required"),
        (
            'name = "x"\nseeds = [0]\nmethods = ["lecoo"]\n[[scenes]]\nname = "city-3"\n',
            "unknown method.*lecoo",
        ),
        (
            'name = "x"\nseeds = [0]\nmethods = ["leco"]\n[[scenes]]\nname = "paris"\n',
            "scene 'paris': unknown scene name",
        ),
        (
            'name = "x"\nseeds = [-1]\nmethods = ["leco"]\n[[scenes]]\nname = "city-3"\n',
            "seeds are non-negative",
        ),
        (
            'name = "x"\nseeds = [0]\nmethods = ["leco"]\n[[scenes]]\nname = "lego"\n'
            '[[scenes]]\nname = "lego"\n',
            "named twice: lego",
        ),
        (
            'name = "x"\nseeds = [0]\nmethods = ["leco"]\n[[scenes]]\nname = "lego"\n'
            "budget_min = 0\n",
            "budget_min: Input should be greater than 0",
        ),
        ('name = "x"\nseeds = [0\n', "not valid TOML"),
    ],
)
def test_a_bad_suite_file_is_refused_naming_what_is_wrong(tmp_path, text, message):
    with pytest.raises(InvalidInput, match=message):
        load_suite(write(tmp_path, text))


def test_narrowing_keeps_the_suites_order_and_refuses_scenes_it_does_not_hold():
    held = load_suite("held-out")
    small = narrowed(held, ["leco", "leco-2026-11-25"], [0], ["village-1", "city-31"])
    assert [s.name for s in small.scenes] == ["city-31", "village-1"]
    assert small.methods == ["leco", "leco-2026-11-25"] and small.seeds == [0]
    with pytest.raises(InvalidInput, match="city-0 not in suite held-out"):
        narrowed(held, None, None, ["city-0"])
    with pytest.raises(InvalidInput, match="unknown scene name"):
        check_name("city")


def test_a_suite_folder_keeps_the_commit_it_was_frozen_at(tmp_path):
    stamp = freeze(tmp_path, ROOT, print)
    assert re.fullmatch(r"[0-9a-f]{40}", stamp["commit"])
    assert (tmp_path / "source" / "bench" / "suite.py").is_file() or (
        tmp_path / "source" / "cli" / "main.py"
    ).is_file()
    assert freeze(tmp_path, ROOT, print) == stamp  # the same commit: reused
    other = {**stamp, "commit": "0" * 40}
    (tmp_path / "source.json").write_text(json.dumps(other))
    with pytest.raises(InvalidInput, match="holds runs of commit 0000000000.*choose another --out"):
        freeze(tmp_path, ROOT, print)


def test_a_suite_can_freeze_a_named_commit_and_refuses_one_that_is_not(tmp_path):
    head = freeze(tmp_path / "a", ROOT, print)["commit"]
    named = freeze(tmp_path / "b", ROOT, print, head[:12])
    assert named["commit"] == head  # the full hash is kept
    assert named["dirty_checkout"] is False  # a named commit is what it is, whatever the checkout
    with pytest.raises(Failed, match="rev-parse"):
        freeze(tmp_path / "c", ROOT, print, "no-such-commit")


def toy_run(variant: str, seed: int, psnr: float) -> dict:
    curve = [
        {"step": 10, "phase": "main", "psnr": 12.0},
        {"step": 20, "phase": "main", "wall_time_s": 30.0, "val_psnr": psnr},
    ]
    return {
        "variant": variant,
        "method": variant.split("+")[0],
        "label": variant,
        "seed": seed,
        "summary": {"val": {"psnr": psnr}},
        "curve": curve,
    }


def test_records_keep_one_suite_at_one_commit_and_give_back_only_runs_of_the_asked_spec(tmp_path):
    suite = load_suite("held-out")
    scene = suite.scenes[0]
    records = tmp_path / "records"
    open_records(records, "held-out", "a" * 40)
    open_records(records, "held-out", "a" * 40)  # the same suite and commit: taken again
    with pytest.raises(InvalidInput, match="at commit aaaaaaaaaa, not held-out at bbbbbbbbbb"):
        open_records(records, "held-out", "b" * 40)
    with pytest.raises(InvalidInput, match="not dev at"):
        open_records(records, "dev", "a" * 40)

    spec = lambda method, sets=(): spec_of(suite, scene, 1, method, list(sets))
    machine = {"cpu": "toy", "cores": 2, "torch": "x"}
    runs = [
        condensed(toy_run(m, 1, 20.0 + i), spec(m), machine, "leco bench ...", "exact")
        for i, m in enumerate(["leco", "prop"])
    ]
    assert [p["step"] for p in runs[0]["curve"]] == [20]  # tracked validations only
    add_runs(records, scene.name, 1, runs)
    assert recorded_runs(records, scene.name, 0) == []  # another seed: nothing recorded
    asked = {"leco": spec("leco"), "prop": spec("prop", ["guided.dilate=2"]), "grid": spec("grid")}
    assert set(reusable(recorded_runs(records, scene.name, 1), asked)) == {"leco"}
    # a run trained again replaces the recorded one of its method, and keeps the others
    add_runs(records, scene.name, 1, [{**runs[0], "summary": {"val": {"psnr": 25.0}}}])
    kept = {
        r["variant"]: r["summary"]["val"]["psnr"] for r in recorded_runs(records, scene.name, 1)
    }
    assert kept == {"leco": 25.0, "prop": 21.0}
    record_path(records, scene.name, 1).write_text("{")
    with pytest.raises(InvalidInput, match="not a suite record"):
        recorded_runs(records, scene.name, 1)


def test_rank_counts_the_rows_ahead():
    rows = {"a": {"psnr": 20.0}, "b": {"psnr": 22.0}, "c": {"psnr": None}, "d": {"psnr": 21.0}}
    assert [rank_of(rows, n) for n in "abcd"] == [3, 1, None, 2]


@pytest.mark.slow
def test_a_suite_runs_end_to_end_at_the_smoke_profile(tmp_path, monkeypatch, capsys):
    """Two tiny cities, two methods, one seed: a table per scene, the mean over scenes per
    method, the commit the runs trained."""
    monkeypatch.setenv("LECO_SCENES", str(tmp_path / "scenes"))
    path = write(
        tmp_path,
        'name = "tiny-pair"\ndescription = "two tiny cities"\nprofile = "smoke"\nseeds = [0]\n'
        'methods = ["leco", "switch"]\n'
        '[[scenes]]\nname = "tiny-0"\neval_every_s = 0.3\n'
        '[[scenes]]\nname = "tiny-1"\neval_every_s = 0.3\n',
    )
    out = tmp_path / "out"
    assert main(["bench", "--suite", path, "--out", str(out)]) == 0
    summary = json.loads((out / "suite.json").read_text())
    assert Suite.model_validate(summary["suite"]).name == "tiny-pair"
    assert summary["commit"] == json.loads((out / "source.json").read_text())["commit"]
    assert set(summary["scenes"]) == {"tiny-0", "tiny-1"}
    for name, scene in summary["scenes"].items():
        assert (tmp_path / "scenes" / name / "gt" / "scene.json").is_file()
        assert set(scene["rows"]) == {"leco", "switch"}
        assert scene["occupancy_reference"].startswith("exact ground truth")
        leco = scene["rows"]["leco"]
        assert 5 < leco["psnr"] < 40 and leco["psnr_by_seed"] == [leco["psnr"]]
        assert 0 <= leco["occupancy_f1"] <= 1 and scene["rows"]["switch"]["occupancy_f1"] is None
        assert leco["tracked"] and leco["steps"] > 0
    for name, method in summary["methods"].items():
        psnrs = [s["rows"][name]["psnr"] for s in summary["scenes"].values()]
        assert method["mean_psnr"] == pytest.approx(sum(psnrs) / 2) and method["scenes"] == 2
    assert sum(len(m["best_on"]) for m in summary["methods"].values()) == 2
    report = (out / "report.md").read_text()
    assert "# Suite `tiny-pair`" in report and "## Mean over scenes" in report
    assert "## tiny-0" in report and "## tiny-1" in report
    assert summary["commit"][:10] in report
    # run again: every run is reused, nothing trains
    first = {n: s["rows"]["leco"]["psnr"] for n, s in summary["scenes"].items()}
    assert main(["bench", "--suite", path, "--out", str(out)]) == 0
    again = json.loads((out / "suite.json").read_text())
    assert {n: s["rows"]["leco"]["psnr"] for n, s in again["scenes"].items()} == first
    # another checkout continues from committed records at the commit they were made at: a third
    # method trains, the recorded ones do not
    records = tmp_path / "committed-records"
    shutil.copytree(out / "records", records)
    capsys.readouterr()
    words = ["bench", "--suite", path, "--out", str(tmp_path / "later"), "--records", str(records)]
    words += ["--commit", summary["commit"], "--methods", "leco,switch,prop", "--scenes", "tiny-0"]
    assert main(words) == 0
    log = capsys.readouterr().err
    # the suite asks its one `leco bench` for the method the records lack, and for nothing else
    assert log.count("[suite] tiny-0 seed 0: leco bench") == 1 and "--methods prop " in log
    later = json.loads((tmp_path / "later" / "suite.json").read_text())
    assert later["scenes"]["tiny-0"]["rows"]["leco"]["psnr"] == first["tiny-0"]
    assert set(later["scenes"]["tiny-0"]["rows"]) == {"leco", "switch", "prop"}
    assert {r["variant"] for r in recorded_runs(records, "tiny-0", 0)} == {"leco", "switch", "prop"}

"""The benchmark report's "what reaches the main network" and "recall by height layer" tables, with
summaries that have the figures and summaries from before them (printed n/a), and the
recall-by-layer figure."""

from pathlib import Path

import pytest
from PIL import Image

from bench.analysis import layer_recalls, measured_or_blank
from bench.plots import recall_by_layer
from bench.report import write_report


def layers(recalls: list[float | None]) -> list[dict]:
    """Eight layers, 100 reference cells at the bottom and 10 fewer per layer up; None: none there
    (set to 0)."""
    return [
        {
            "z_min": i / 8,
            "z_max": (i + 1) / 8,
            "reference_cells": 100 - 10 * i if r is not None else 0,
            "predicted_cells": 0,
            "recall": r,
        }
        for i, r in enumerate(recalls)
    ]


def summary(method: str, seed: int) -> dict:
    """A summary with the evaluation-time accounting: LeCO drops the ground, the grid keeps it."""
    base = {
        "rays_per_s": 1000.0,
        "samples_per_ray": 20.0,
        "val": {"psnr": 20.0},
        "config": {"use_gpu": False},
        "wall_time_s": {"total": 60.0},
        "steps": {"total": 100},
        "rays": {
            "selection": "all 2,400 pixels of the 2 validation views",
            "rays": 2400,
            "bins": 8,
            "occupancy_ratio": 1.0,
            "samples_per_hit_ray": 32.0,
            "hit_ray_fraction": 0.9,
            "depth_source": "exact depth maps",
            "surface_rays": 1500,
            "surface_bin_kept": 1.0,
            "foreground_opacity": 0.9,
        },
        "sampling": {"occupancy_ratio": 1.0, "samples_per_hit_ray": 32.0},
        "occupancy": None,
    }
    if method == "leco":
        base["rays"].update(
            occupancy_ratio=0.10 + 0.02 * seed, surface_bin_kept=0.7, foreground_opacity=0.6
        )
        base["sampling"].update(occupancy_ratio=0.12, fallback_fraction=0.05)
        base["occupancy"] = {
            "recall": 0.8,
            "top1_recall": 0.6,
            "ground_recall": 0.1 * seed,
            "ground_cells": 1000,
            "layers": layers([0.0 + 0.2 * seed, 0.9, 1.0, 1.0, 1.0, 1.0, None, None]),
        }
    elif method == "grid":
        base["rays"].update(occupancy_ratio=0.3, surface_bin_kept=0.95)
        base["occupancy"] = {
            "recall": 0.9,
            "ground_recall": 0.95,
            "ground_cells": 1000,
            "layers": layers([0.95, 0.9, 0.9, 0.9, 0.8, 0.8, None, None]),
        }
    return base


def old_summary() -> dict:
    """A summary written before the accounting: no rays, no sampling, an occupancy without
    layers."""
    return {
        "rays_per_s": 900.0,
        "samples_per_ray": 20.0,
        "val": {"psnr": 19.0},
        "config": {"use_gpu": False},
        "occupancy": {"recall": 0.7, "f1": 0.4},
    }


def run(variant: str, seed: int, data: dict, label: str | None = None) -> dict:
    return {
        "variant": variant,
        "method": variant.split("-")[0],
        "label": label or variant,
        "ablation": False,
        "seed": seed,
        "summary": data,
        "curve": [],
        "run_dir": "/nowhere",
    }


def results(runs: list[dict], figures: dict | None = None) -> dict:
    return {
        "runs": runs,
        "figures": figures or {},
        "speedups": {},
        "equal_psnr": [],
        "targets": [],
        "plan": {
            "scene": "tiny",
            "profile": "smoke",
            "budget_min": None,
            "seeds": [0, 1],
            "backend": "local",
            "workers": 1,
            "eval_views": 2,
        },
        "machine": {"cpu": "test", "cores": 2, "torch": "x", "python": "3.11"},
        "finished_at": "now",
        "command": "leco bench",
        "occupancy_reference": "exact ground truth",
    }


def section(report: str, title: str) -> list[str]:
    """The table rows under a heading, as lists of cells."""
    lines = report.split(f"## {title}\n\n", 1)[1].split("\n\n", 1)[0].splitlines()
    return [[c.strip() for c in line.strip("|").split("|")] for line in lines]


def test_measured_or_blank_tells_not_applicable_from_not_measured():
    runs = [
        run("leco", 0, summary("leco", 0)),
        run("switch", 0, summary("switch", 0)),
        run("old", 0, old_summary()),
    ]
    assert measured_or_blank(runs, "leco", "sampling.fallback_fraction", "sampling") == (0.05, None)
    assert measured_or_blank(runs, "switch", "sampling.fallback_fraction", "sampling") == "–"
    assert measured_or_blank(runs, "old", "sampling.fallback_fraction", "sampling") == "n/a"


def test_the_report_counts_what_reaches_the_main_network_alike(tmp_path):
    runs = [run(m, seed, summary(m, seed)) for seed in (0, 1) for m in ("leco", "switch", "grid")]
    runs.append(run("old", 0, old_summary(), "Old run"))
    write_report(results(runs, {"recall_by_layer": "figures/recall_by_layer.png"}), tmp_path)
    report = (tmp_path / "report.md").read_text()
    # the tables from before are all still there
    assert "## Occupancy (the paper's Table 1)" in report
    rows = {r[0]: r[1:] for r in section(report, "What reaches the main network, counted alike")}
    assert rows["method"] == [
        "occupancy ratio (validation rays)",
        "occupancy ratio (training mean)",
        "samples per hit ray (validation)",
        "fallback share",
        "surface bin kept",
        "foreground opacity on surface rays",
        "recall (its threshold)",
        "recall (top-1)",
        "ground recall",
    ]
    # LeCO's ratio over its two seeds: 10% and 12% -> 11.0% ± 1.4%; its ground recall 0.0 and 0.1.
    assert rows["leco"] == [
        "11.0% ± 1.4%",
        "12.0% ± 0.0%",
        "32.0 ± 0.0",
        "5.0% ± 0.0%",
        "70.0% ± 0.0%",
        "0.600 ± 0.000",
        "0.800 ± 0.000",
        "0.600 ± 0.000",
        "0.050 ± 0.071",
    ]
    assert rows["switch"][:6] == [
        "100.0% ± 0.0%",
        "100.0% ± 0.0%",
        "32.0 ± 0.0",
        "–",
        "100.0% ± 0.0%",
        "0.900 ± 0.000",
    ]
    assert rows["switch"][6:] == ["–"] * 3  # vanilla has no occupancy to score
    assert rows["grid"][3] == "–" and rows["grid"][7] == "–" and rows["grid"][8] == "0.950 ± 0.000"
    assert rows["Old run"] == ["n/a", "n/a", "n/a", "n/a", "n/a", "n/a", "0.700", "n/a", "n/a"]
    assert (
        "Validation rays: all 2,400 pixels of the 2 validation views, 8 bins per ray; surfaces "
        "from exact" in report
    )

    layer_rows = section(report, "Recall by height layer")
    # methods with layers only
    assert layer_rows[0] == ["height (box z, 0-1)", "reference cells", "leco", "grid"]
    # the top layer first; nothing stands there
    assert layer_rows[2] == ["0.875–1.000", "0", "–", "–"]
    assert layer_rows[4] == ["0.625–0.750", "50", "1.000 ± 0.000", "0.800 ± 0.000"]
    assert layer_rows[9] == ["0.000–0.125", "100", "0.100 ± 0.141", "0.950 ± 0.000"]
    assert layer_rows[10] == ["ground", "1,000", "0.050 ± 0.071", "0.950 ± 0.000"]
    assert "Figure: `figures/recall_by_layer.png`." in report


def test_a_report_from_older_summaries_only_prints_n_a(tmp_path):
    runs = [run("leco", 0, old_summary()), run("switch", 0, {**old_summary(), "occupancy": None})]
    write_report(results(runs), tmp_path)
    report = (tmp_path / "report.md").read_text()
    rows = {r[0]: r[1:] for r in section(report, "What reaches the main network, counted alike")}
    assert rows["leco"] == ["n/a"] * 6 + ["0.700", "n/a", "n/a"]
    assert rows["switch"] == ["n/a"] * 6 + ["–"] * 3
    assert "## Recall by height layer" not in report and "Validation rays:" not in report


def test_layer_recalls_and_the_figure(tmp_path):
    runs = [run(m, seed, summary(m, seed)) for seed in (0, 1) for m in ("leco", "switch", "grid")]
    means = layer_recalls(runs)
    assert list(means) == ["leco", "grid"]
    assert means["leco"][0]["recall"] == pytest.approx(0.1) and means["leco"][7]["recall"] is None
    assert means["leco"][0]["recall_std"] == pytest.approx(0.1414, abs=1e-4)
    assert means["grid"][1] == {
        "z_min": 0.125,
        "z_max": 0.25,
        "reference_cells": 90,
        "recall": pytest.approx(0.9),
        "recall_std": 0.0,
    }
    name = recall_by_layer(runs, tmp_path / "recall_by_layer.png")
    with Image.open(tmp_path / name) as image:
        assert image.format == "PNG" and image.width > 300
    assert recall_by_layer([run("old", 0, old_summary())], tmp_path / "none.png") is None


def test_against_vanilla_scores_occupancy_rules_and_every_methods_surfaces(tiny_scene, monkeypatch):
    """The bench's path for scenes without depth maps, with the tiny city's exact maps standing in
    for the vanilla model's (rendering them is what the slow lego test covers) and untrained smoke
    networks."""
    import torch

    import bench.reference as reference
    from model.methods import get_method
    from workers.config import TrainConfig

    views = tiny_scene.splits["val"]
    cfg = TrainConfig(method="switch", profile="smoke")
    profile = cfg.resolved_profile()
    switch = get_method("switch")(profile)
    torch.manual_seed(0)
    models = switch.build(len(tiny_scene.train) + len(views), tiny_scene.bounds.aabb)

    # vanilla's sampler with the exact occupancy to score and a rule that keeps nothing
    class Exact(type(switch)):
        def final_occupancy(self, models):
            return tiny_scene.occupancy.lookup

        def decision_rules(self, models):
            return {"none": lambda p: torch.zeros(len(p), dtype=torch.bool)}

    monkeypatch.setattr(
        reference, "vanilla_depth_maps", lambda run: (list(views.depth), (tiny_scene, views))
    )
    monkeypatch.setattr(
        reference, "load_final", lambda run, device: (cfg, tiny_scene, Exact(profile), models)
    )
    out = reference.against_vanilla(
        Path("runs/switch-seed0"),
        [Path("runs/grid-seed0")],
        [Path("runs/switch-seed0"), Path("runs/grid-seed0")],
    )
    occupancy = out["occupancy"]["runs/grid-seed0"]
    assert occupancy["reference"] == "depth of the trained vanilla Switch-NeRF (switch-seed0)"
    assert occupancy["none_recall"] == 0.0 and occupancy["none_ground_recall"] == 0.0
    assert len(occupancy["layers"]) == 8 and occupancy["ground_cells"] > 0
    rays = out["rays"]["runs/switch-seed0"]
    assert rays["depth_source"] == "depth of the trained vanilla Switch-NeRF (switch-seed0)"
    assert (
        rays["occupancy_ratio"] == 1.0
        and rays["surface_bin_kept"] == 1.0
        and rays["surface_rays"] > 1000
    )
    assert set(out["rays"]) == {"runs/switch-seed0", "runs/grid-seed0"}

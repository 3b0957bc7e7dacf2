"""results.json and report.md: the paper's Tables 1 and 3 (and 4/5 for ablations) from measured
runs."""

from __future__ import annotations

import json
import os
import platform
from pathlib import Path

import torch

from bench.analysis import (
    TRACKED_STEPS,
    families,
    get,
    layer_recalls,
    main_curve,
    mean_std,
    measured_or_blank,
    per_variant,
    roles,
    time_to_psnr,
    tracked_by_step,
)
from bench.variants import ABLATIONS, RUNGS, TABLE_REFERENCES
from model.methods import METHODS

PAPER_NOTE = (
    "Paper (Mega-NeRF scenes, 8 GPUs): LeCO ~2.5x faster than Switch-NeRF at equal or better PSNR, "
    "occupancy network 0.15M parameters vs a 2.1M-cell grid, occupancy ratio below the grid's."
)


def machine() -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    info = {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "os": platform.platform(),
    }
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    return info


def cell(value: tuple[float | None, float | None] | float | None, spec: str) -> str:
    mean, std = value if isinstance(value, tuple) else (value, None)
    if mean is None:
        return "n/a"
    text = format(mean, spec)
    return f"{text} ± {format(std, spec)}" if std is not None else text


def table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def occupancy_table(runs: list[dict], names: list[str], labels: dict) -> str:
    stats = {
        k: per_variant(runs, f"occupancy.{k}")
        for k in ("accuracy", "precision", "recall", "f1", "params", "occupancy_ratio")
    }
    rows = [
        [
            labels[n],
            cell(stats["accuracy"][n], ".3f"),
            cell(stats["precision"][n], ".3f"),
            cell(stats["recall"][n], ".3f"),
            cell(stats["f1"][n], ".3f"),
            cell(stats["params"][n], ",.0f"),
            cell(stats["occupancy_ratio"][n], ".1%"),
        ]
        for n in names
    ]
    return table(
        ["method", "accuracy", "precision", "recall", "F1", "parameters", "occupancy ratio"], rows
    )


# What reaches the main network (columns: header, summary path, format, the block that says it was
# measured).
COUNTED_ALIKE = (
    ("occupancy ratio (validation rays)", "rays.occupancy_ratio", ".1%", "rays"),
    ("occupancy ratio (training mean)", "sampling.occupancy_ratio", ".1%", "sampling"),
    ("samples per hit ray (validation)", "rays.samples_per_hit_ray", ".1f", "rays"),
    ("fallback share", "sampling.fallback_fraction", ".1%", "sampling"),
    ("surface bin kept", "rays.surface_bin_kept", ".1%", "rays.depth_source"),
    ("foreground opacity on surface rays", "rays.foreground_opacity", ".3f", "rays.depth_source"),
    ("recall (its threshold)", "occupancy.recall", ".3f", "occupancy.layers"),
    ("recall (top-1)", "occupancy.top1_recall", ".3f", "occupancy.layers"),
    ("ground recall", "occupancy.ground_recall", ".3f", "occupancy.layers"),
)


def counted_cell(runs: list[dict], name: str, path: str, spec: str, parent: str) -> str:
    method = next((METHODS.get(r["method"]) for r in runs if r["variant"] == name), None)
    if path.startswith("occupancy.") and method is not None and not method.has_occupancy:
        return "–"  # vanilla: no occupancy to score
    value = measured_or_blank(runs, name, path, parent)
    return value if isinstance(value, str) else cell(value, spec)


def counted_alike_table(runs: list[dict], names: list[str], labels: dict) -> str:
    """Per method, what reaches the main network counted on the same coarse bins, whatever put it
    there."""
    rows = [
        [labels[n]]
        + [counted_cell(runs, n, path, spec, parent) for _, path, spec, parent in COUNTED_ALIKE]
        for n in names
    ]
    return table(["method"] + [header for header, *_ in COUNTED_ALIKE], rows)


def counted_alike_notes(runs: list[dict]) -> str:
    """What the table above counted: which rays, how many bins, and where the surfaces came from."""
    block = next((r["summary"]["rays"] for r in runs if r["summary"].get("rays")), None)
    notes = [
        "Each hit ray's foreground segment is cut into LeCO's coarse bins (every method counted on "
        "the same bins); a bin reaches the main network when at least one main-network sample lies "
        "in it, whatever put it there (O, dilation, a fallback, a proposal, a grid cell). Only "
        "rays that cross the box count. Surface bin kept: the share of rays with a visible surface "
        "in the box whose surface bin reaches the main network; foreground opacity: the summed "
        "render weights of the main samples on those rays. Recall (top-1): O's own top-1 rule "
        "beside the threshold LeCO samples with. Ground recall: each (x, y) column's lowest "
        'occupied cell the views observe. "–": does not apply to the method; "n/a": not '
        "measured (a run from before these figures)."
    ]
    if block:
        notes.append(
            f"Validation rays: {block.get('selection', 'n/a')}, {block.get('bins', 'n/a')} bins "
            "per ray; surfaces from "
            f"{block.get('depth_source') or block.get('surface_note') or 'n/a'}."
        )
    return "\n\n".join(notes)


def layer_table(runs: list[dict], names: list[str], labels: dict) -> str | None:
    """Recall by height layer, one column per method, the top layer first (as heights read on a
    page), and the ground's recall below."""
    layers = layer_recalls(runs)
    shown = [n for n in names if n in layers]
    if not shown:
        return None
    first = layers[shown[0]]  # every method is scored on the same reference cells
    rows = []
    for i in reversed(range(len(first))):
        recalls = [
            cell((layers[n][i]["recall"], layers[n][i]["recall_std"]), ".3f")
            if first[i]["reference_cells"]
            else "–"
            for n in shown
        ]  # nothing stands at that height
        rows.append(
            [f"{first[i]['z_min']:.3f}–{first[i]['z_max']:.3f}", str(first[i]["reference_cells"])]
            + recalls
        )
    ground = per_variant(runs, "occupancy.ground_recall")
    cells = get(
        next(r["summary"] for r in runs if r["variant"] == shown[0]), "occupancy.ground_cells"
    )
    rows.append(["ground", cell(cells, ",.0f")] + [cell(ground[n], ".3f") for n in shown])
    return table(["height (box z, 0-1)", "reference cells"] + [labels[n] for n in shown], rows)


def quality_table(runs: list[dict], names: list[str], labels: dict) -> str:
    s = {
        k: per_variant(runs, k)
        for k in (
            "val.psnr",
            "val.ssim",
            "val.lpips_vgg",
            "val.lpips_alex",
            "wall_time_s.total",
            "peak_memory_mb",
            "activation_memory_mb",
            "rays_per_s",
            "samples_per_ray",
            "steps.total",
        )
    }
    minutes = {
        n: (None if m is None else m / 60, None if sd is None else sd / 60)
        for n, (m, sd) in s["wall_time_s.total"].items()
    }
    rows = [
        [
            labels[n],
            cell(s["val.psnr"][n], ".2f"),
            cell(s["val.ssim"][n], ".3f"),
            cell(s["val.lpips_vgg"][n], ".3f"),
            cell(s["val.lpips_alex"][n], ".3f"),
            cell(minutes[n], ".2f"),
            cell(s["peak_memory_mb"][n], ",.0f"),
            cell(s["activation_memory_mb"][n], ".1f"),
            cell(s["rays_per_s"][n], ",.0f"),
            cell(s["samples_per_ray"][n], ".1f"),
            cell(s["steps.total"][n], ",.0f"),
        ]
        for n in names
    ]
    return table(
        [
            "method",
            "PSNR",
            "SSIM",
            "LPIPS (VGG)",
            "LPIPS (Alex)",
            "time (min)",
            "peak memory (MB)",
            "activations (MB/step)",
            "rays/s (main)",
            "samples/ray",
            "steps",
        ],
        rows,
    )


def ladder_table(runs: list[dict]) -> str:
    """Each rung's PSNR, when it reached vanilla's best tracked PSNR, and what its occupancy and
    sampler did."""
    names = [n for n in dict.fromkeys(r["variant"] for r in runs if r.get("ladder"))]
    ours, ref = roles()
    names += [ours] if any(r["variant"] == ours for r in runs) else []
    labels = {r["variant"]: r["label"] for r in runs}
    labels[ours] = RUNGS[-1][1]
    reach: dict[str, list[float | None]] = {n: [] for n in names}  # per seed; None: never reached
    for r in runs:
        vanilla = [v for v in runs if v["variant"] == ref and v["seed"] == r["seed"]]
        if r["variant"] in reach and vanilla and main_curve(vanilla[0]):
            target = max(p for _, p in main_curve(vanilla[0]))
            reach[r["variant"]].append(time_to_psnr(main_curve(r), target))
    s = {
        k: per_variant(runs, k)
        for k in (
            "val.psnr",
            "occupancy.recall",
            "occupancy.f1",
            "occupancy.occupancy_ratio",
            "samples_per_ray",
            "rays_per_s",
        )
    }
    minutes = lambda values: (
        "never" if not values or None in values else cell(mean_std([v / 60 for v in values]), ".2f")
    )
    rows = [
        [
            labels[n],
            cell(s["val.psnr"][n], ".2f"),
            minutes(reach[n]),
            cell(s["occupancy.recall"][n], ".3f"),
            cell(s["occupancy.f1"][n], ".3f"),
            cell(s["occupancy.occupancy_ratio"][n], ".1%"),
            cell(s["samples_per_ray"][n], ".1f"),
            cell(s["rays_per_s"][n], ",.0f"),
        ]
        for n in names
    ]
    return table(
        [
            "rung (cumulative)",
            "val PSNR",
            "min to vanilla's best tracked PSNR",
            "recall",
            "F1",
            "occupancy ratio",
            "samples/ray",
            "rays/s (main)",
        ],
        rows,
    )


def sweep_table(runs: list[dict]) -> str:
    """Every method at each sampling budget: cost (samples per ray, rays/s) against final
    quality."""
    from bench.plots import sweep_points

    rows = []
    for rs in sweep_points(runs).values():
        for r in rs:
            s = r["summary"]
            label = r["label"] if r.get("sweep") else f"{r['label']} (default)"
            rows.append(
                [
                    label,
                    cell(s.get("samples_per_ray"), ".1f"),
                    cell(s.get("rays_per_s"), ",.0f"),
                    cell(get(s, "val.psnr"), ".2f"),
                    cell(get(s, "val.ssim"), ".3f"),
                    cell(get(s, "steps.total"), ",.0f"),
                ]
            )
    return table(
        ["method, sampling budget", "samples/ray", "rays/s (main)", "val PSNR", "SSIM", "steps"],
        rows,
    )


def table_rows(runs: list[dict], table_name: str) -> list[str]:
    """The variants of one of the paper's ablation tables that ran, with its reference rows
    first."""
    refs = [roles()[0] if n == "ours" else n for n in TABLE_REFERENCES[table_name]]
    ran = set(r["variant"] for r in runs)
    return [n for n in refs if n is not None and n in ran] + [
        n for n, v in ABLATIONS.items() if v.table == table_name and n in ran
    ]


def grid_resolution_table(runs: list[dict]) -> str:
    """Table 7: the grid at 128^3 and 256^3 against LeCO: quality, training time and memory."""
    names = table_rows(runs, "7")
    labels = {r["variant"]: r["label"] for r in runs}
    s = {
        k: per_variant(runs, k)
        for k in (
            "val.psnr",
            "val.ssim",
            "val.lpips_vgg",
            "wall_time_s.total",
            "steps.total",
            "rays_per_s",
            "peak_memory_mb",
            "occupancy.params",
        )
    }
    rows = [
        [
            labels[n],
            cell(s["val.psnr"][n], ".2f"),
            cell(s["val.ssim"][n], ".3f"),
            cell(s["val.lpips_vgg"][n], ".3f"),
            cell(s["wall_time_s.total"][n], ",.0f"),
            cell(s["steps.total"][n], ",.0f"),
            cell(s["rays_per_s"][n], ",.0f"),
            cell(s["peak_memory_mb"][n], ",.0f"),
            cell(s["occupancy.params"][n], ",.0f"),
        ]
        for n in names
    ]
    return table(
        [
            "method",
            "PSNR",
            "SSIM",
            "LPIPS (VGG)",
            "time (s)",
            "steps",
            "rays/s (main)",
            "peak memory (MB)",
            "occupancy parameters / cells",
        ],
        rows,
    )


def empty_expert_table(runs: list[dict]) -> str:
    """Table 9: the empty-space expert as an identity layer (LeCO's), a 4-layer MLP, or a scene
    expert's size."""
    names = table_rows(runs, "9")
    labels = {r["variant"]: r["label"] for r in runs}
    labels[roles()[0]] = "E_e: identity (LeCO)"
    s = {
        k: per_variant(runs, k)
        for k in (
            "val.psnr",
            "val.ssim",
            "val.lpips_vgg",
            "val.lpips_alex",
            "occupancy.f1",
            "occupancy.recall",
            "occupancy.empty_fraction",
        )
    }
    rows = [
        [
            labels[n],
            cell(s["val.psnr"][n], ".2f"),
            cell(s["val.ssim"][n], ".3f"),
            cell(s["val.lpips_vgg"][n], ".3f"),
            cell(s["val.lpips_alex"][n], ".3f"),
            cell(s["occupancy.f1"][n], ".3f"),
            cell(s["occupancy.recall"][n], ".3f"),
            cell(s["occupancy.empty_fraction"][n], ".1%"),
        ]
        for n in names
    ]
    return table(
        [
            "empty-space expert",
            "PSNR",
            "SSIM",
            "LPIPS (VGG)",
            "LPIPS (Alex)",
            "occupancy F1",
            "recall",
            "points to E_e",
        ],
        rows,
    )


def ablation_table(runs: list[dict]) -> str:
    names = table_rows(runs, "4/5")
    labels = {r["variant"]: r["label"] for r in runs}
    hmoe = {}
    for n in names:  # the HMoE's own rendering at the end of phase 1 (what Table 4 scores)
        ends = []
        for r in runs:
            points = [p for p in r["curve"] if p.get("phase") == "occupancy" and "val_psnr" in p]
            if r["variant"] == n and points:
                ends.append(points[-1]["val_psnr"])
        hmoe[n] = mean_std(ends)
    s = {
        k: per_variant(runs, k)
        for k in (
            "occupancy.empty_fraction",
            "occupancy.f1",
            "occupancy.recall",
            "occupancy.precision",
            "val.psnr",
            "val.ssim",
            "val.lpips_vgg",
            "val.lpips_alex",
        )
    }
    rows = [
        [
            labels[n],
            cell(hmoe[n], ".2f"),
            cell(s["occupancy.empty_fraction"][n], ".1%"),
            cell(s["occupancy.f1"][n], ".3f"),
            cell(s["occupancy.recall"][n], ".3f"),
            cell(s["occupancy.precision"][n], ".3f"),
            cell(s["val.psnr"][n], ".2f"),
            cell(s["val.ssim"][n], ".3f"),
            cell(s["val.lpips_vgg"][n], ".3f"),
            cell(s["val.lpips_alex"][n], ".3f"),
        ]
        for n in names
    ]
    return table(
        [
            "variant",
            "phase-1 HMoE PSNR",
            "points to E_e",
            "occupancy F1",
            "recall",
            "precision",
            "guided PSNR",
            "SSIM",
            "LPIPS (VGG)",
            "LPIPS (Alex)",
        ],
        rows,
    )


def write_results(results: dict, out: Path) -> None:
    tmp = out / "results.json.tmp"
    tmp.write_text(json.dumps(results, indent=1, default=float))
    tmp.replace(out / "results.json")


def scale_text(plan: dict) -> str:
    """Which image scale the runs trained and were scored at (results written before downscale
    existed: 1)."""
    factor, asked = plan.get("downscale", 1), plan.get("downscale_asked")
    where = "asked for with --downscale" if asked is not None else "the scene's own"
    return f"images at 1/{factor} scale for training and validation alike ({where})"


def paper_tables(numbers: list[str]) -> str:
    """ "Table 3", "Tables 3 and 6"."""
    if len(numbers) == 1:
        return f"Table {numbers[0]}"
    return f"Tables {', '.join(numbers[:-1])} and {numbers[-1]}"


def tracked_table(runs: list[dict], names: list[str], labels: dict) -> str:
    """The tracked validation PSNR at fixed main steps, beside the main steps and phase-1 time
    each run got: a sampler that is ahead at equal steps but behind at equal time pays in cost."""
    at = tracked_by_step(runs)
    steps = per_variant(runs, "steps.phases.main")
    phase1 = per_variant(runs, "wall_time_s.phases.occupancy")
    rows = [
        [labels[n]]
        + [cell(at[n][step], ".2f") for step in TRACKED_STEPS]
        + [cell(steps[n], ",.0f"), cell(phase1[n], ".0f")]
        for n in names
    ]
    header = ["method"] + [f"PSNR at main step {s:,}" for s in TRACKED_STEPS]
    return table(header + ["main steps", "phase 1 (s)"], rows)


def family_sections(block: dict, labels: dict, plan: dict, several: bool) -> list[str]:
    """A family's "ours" against the other methods of its family: speed-ups, equal PSNR, targets.
    With several families each section names the family it judges."""
    parts: list[str] = []
    ours = block.get("ours")
    of = f" ({METHODS[ours].family} family)" if several and ours in METHODS else ""
    speed = block["speedups"]
    if speed:
        parts += [f"## Speed-up of {labels.get(ours, ours)}{of}", ""]
        ratio = lambda value: "n/a" if value is None else cell(value, ".2f") + "x"
        rows = [
            [
                labels.get(base, base),
                ratio(v["rays_per_s"]),
                ratio(v["time_to_equal_psnr"]),
                ratio(v["time_to_its_best_psnr"]),
                cell(v["samples_per_ray_fraction"], ".1%"),
                cell(v["activation_memory_fraction"], ".1%"),
                cell(v["peak_memory_fraction"], ".1%"),
            ]
            for base, v in speed.items()
        ]
        parts += [
            table(
                [
                    "over",
                    "rays/s",
                    "time to equal PSNR",
                    "time to its best PSNR",
                    "samples per ray (LeCO / it)",
                    "activations (LeCO / it)",
                    "peak memory (LeCO / it)",
                ],
                rows,
            ),
            "",
        ]
        for e in block["equal_psnr"]:
            times = ", ".join(
                f"{labels.get(k, k)} {'n/a' if v is None else f'{v / 60:.2f} min'}"
                for k, v in e["time_s"].items()
            )
            parts.append(
                f"- seed {e['seed']}: equal PSNR {e['target_psnr']:.2f} dB (the best every method "
                f"{'of the family ' if of else ''}reached, on the first {plan['eval_views']} "
                f"validation views) reached after {times}"
            )
        parts.append("")
    if block["targets"]:
        parts += [
            f"## Targets{of}",
            "",
            table(
                ["target", "measured", "met"],
                [
                    [
                        t["target"],
                        t["measured"],
                        {True: "yes", False: "**no**", None: "n/a"}[t["met"]],
                    ]
                    for t in block["targets"]
                ],
            ),
            "",
        ]
        missed = [t for t in block["targets"] if t["met"] is False]
        if missed:
            parts += [
                f"{len(missed)} target(s) missed; docs/RESULTS.md and docs/EXPERIMENTS.md say "
                "what was measured and tried.",
                "",
            ]
    return parts


def write_report(results: dict, out: Path) -> None:
    runs = results["runs"]
    labels = {r["variant"]: r["label"] for r in runs}
    main = [n for n in dict.fromkeys(r["variant"] for r in runs if not r["ablation"])]
    plan, m = results["plan"], results["machine"]
    parts = [
        "# LeCO-NeRF benchmark",
        "",
        f"- scene: `{plan['scene']}`; profile `{plan['profile']}`; "
        + (
            f"wall-clock budget {plan['budget_min']:g} min per method; "
            if plan["budget_min"]
            else "no budget (the profile's step counts); "
        )
        + f"seeds {', '.join(map(str, plan['seeds']))}; backend {plan['backend']} x "
        f"{plan['workers']} worker(s); " + scale_text(plan),
        f"- machine: {m['cpu']}, {m['cores']} cores{', ' + m['gpu'] if m.get('gpu') else ''}; "
        f"torch {m['torch']}; Python {m['python']}; {results['finished_at']}",
        f"- command: `{results['command']}`",
        f"- occupancy reference: {results['occupancy_reference']}",
        "- times are training compute only (evaluation renders and checkpoints excluded for every "
        "method); LeCO's include its occupancy phase, the grid's its update and culling passes.",
        "",
    ]
    if main:
        parts += [
            "## Occupancy (the paper's Table 1)",
            "",
            occupancy_table(runs, main, labels),
            "",
            "## What reaches the main network, counted alike",
            "",
            counted_alike_table(runs, main, labels),
            "",
            counted_alike_notes(runs),
            "",
        ]
        layers = layer_table(runs, main, labels)
        if layers is not None:
            parts += [
                "## Recall by height layer",
                "",
                layers,
                "",
                "Occupied cells the views observe, by height in the box (top layer first), and the "
                "share each method's occupancy keeps; a sampler that keeps the roofs and drops the "
                "ground shows here while its total recall can look fine."
                + (
                    f" Figure: `{results['figures']['recall_by_layer']}`."
                    if results.get("figures", {}).get("recall_by_layer")
                    else ""
                ),
                "",
            ]
        numbers = [METHODS[ours].paper_table for ours, _ in families(runs)] or ["3"]
        parts += [
            f"## Quality, time and memory (the paper's {paper_tables(numbers)})",
            "",
            quality_table(runs, main, labels),
            "",
            "Peak memory is the process's peak RSS on a CPU (runtime, scene and weights included) "
            "and `torch.cuda.max_memory_allocated` on a GPU; activations are the bytes autograd "
            "keeps for one main-network step (workers/memory.py).",
            "",
            "## The tracked curve at equal main steps",
            "",
            tracked_table(runs, main, labels),
            "",
            "The tracked validation views' PSNR interpolated between evaluations (n/a: the run "
            "stopped before that step).",
            "",
        ]
    for block in results.get("families") or [results]:
        parts += family_sections(block, labels, plan, several=len(results.get("families", [])) > 1)
    if any(r.get("ladder") for r in runs):
        parts += [
            "## Ablation ladder",
            "",
            ladder_table(runs),
            "",
            "Each rung adds one change to the one above it; the last is the profile's defaults. "
            "Time to vanilla's best PSNR is on the tracked validation views, LeCO's phase 1 "
            "included.",
            "",
        ]
    if any(r.get("sweep") for r in runs):
        parts += [
            "## Speed against error: sampling budgets",
            "",
            sweep_table(runs),
            "",
            "Each method's own run is its middle point; samples per ray count every main-network "
            "evaluation (vanilla's coarse pass and LeCO's culling pass included). Figures: "
            "`speed_vs_error.png` (PSNR against samples per ray and rays/s), "
            "`sweep_psnr_vs_time.png`.",
            "",
        ]
    tables = {ABLATIONS[r["variant"]].table for r in runs if r["variant"] in ABLATIONS}
    if "4/5" in tables:
        parts += [
            "## Ablation (the paper's Tables 4 and 5)",
            "",
            ablation_table(runs),
            "",
            "Phase-1 HMoE PSNR is the occupancy network's own rendering at the end of phase 1 "
            "(Table 4 scores this); guided PSNR is the Switch-NeRF it then guides (Table 5).",
            "",
        ]
    if "7" in tables:
        parts += [
            "## Grid resolution (the paper's Table 7)",
            "",
            grid_resolution_table(runs),
            "",
            "Time is training compute; under a budget every row trains for the same time, so the "
            "cost of a finer grid shows as fewer steps and lower PSNR instead of a longer run.",
            "",
        ]
    if "9" in tables:
        parts += [
            "## The empty-space expert (the paper's Table 9)",
            "",
            empty_expert_table(runs),
            "",
            "PSNR is the guided Switch-NeRF's; F1 and recall score O at the end of phase 1.",
            "",
        ]
    if results["figures"]:
        parts += ["## Figures", ""] + [f"![{k}]({v})" for k, v in results["figures"].items()] + [""]
    parts += [PAPER_NOTE, ""]
    tmp = out / "report.md.tmp"
    tmp.write_text("\n".join(parts))
    tmp.replace(out / "report.md")


def summary_line(results: dict) -> str:
    ours, ref = roles(results["runs"])
    speed = results["speedups"].get(ref)
    psnr = {n: m for n, (m, _) in per_variant(results["runs"], "val.psnr").items()}
    text = ", ".join(f"{n} {v:.2f} dB" for n, v in psnr.items() if v is not None)
    if speed and speed["rays_per_s"] is not None:
        text += f"; {ours} vs {ref}: {speed['rays_per_s']:.2f}x rays/s"
        if speed["time_to_equal_psnr"] is not None:
            text += f", {speed['time_to_equal_psnr']:.2f}x to equal PSNR"
        best = speed["time_to_its_best_psnr_per_seed"]
        if best:
            text += (
                " and "
                + "/".join("never" if b is None else f"{b:.2f}x" for b in best)
                + f" to {ref}'s best"
            )
    return text


__all__ = ["machine", "write_report", "write_results", "summary_line", "get"]

"""A suite's report.md (bench/suite.py): the mean over scenes per method, a table per scene."""

from __future__ import annotations

from pathlib import Path


def number(value, spec: str) -> str:
    return "–" if value is None else format(value, spec)


def table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def mean_table(summary: dict) -> str:
    methods = summary["methods"]
    order = sorted(methods, key=lambda n: -(methods[n]["mean_psnr"] or float("-inf")))
    rows = [
        [
            methods[n]["label"],
            number(methods[n]["mean_psnr"], ".2f"),
            number(methods[n]["mean_rank"], ".1f"),
            ", ".join(methods[n]["best_on"]) or "–",
        ]
        for n in order
    ]
    return table(["method", "mean PSNR over scenes", "mean rank", "best on"], rows)


def tracked_cell(row: dict) -> str:
    """Each seed's best tracked PSNR and when, and whether the curve ended there."""
    parts = [
        f"{t['best_psnr']:.2f} at {t['best_at_min']:.1f} min"
        + ("" if t["ends_at_best"] else f", ends {t['last_psnr']:.2f}")
        for t in row["tracked"]
    ]
    return "; ".join(parts) or "–"


def scene_table(scene: dict) -> str:
    rows = sorted(scene["rows"].values(), key=lambda r: -(r["psnr"] or float("-inf")))
    return table(
        [
            "method",
            "PSNR",
            "by seed",
            "SSIM",
            "LPIPS (VGG)",
            "occupancy F1",
            "lowest layer recall",
            "steps",
            "tracked best (seed by seed)",
        ],
        [
            [
                r["label"],
                number(r["psnr"], ".2f"),
                " / ".join(number(p, ".2f") for p in r["psnr_by_seed"]),
                number(r["ssim"], ".3f"),
                number(r["lpips_vgg"], ".3f"),
                number(r["occupancy_f1"], ".3f"),
                number(r["lowest_layer_recall"], ".3f"),
                number(r["steps"], ",.0f"),
                tracked_cell(r),
            ]
            for r in rows
        ],
    )


def write_report(summary: dict, path: Path) -> None:
    suite = summary["suite"]
    parts = [
        f"# Suite `{suite['name']}`",
        "",
        suite["description"],
        "",
        f"- commit {summary['commit'][:10]} (a frozen copy"
        + (", the checkout had uncommitted changes" if summary["dirty_checkout"] else "")
        + f"); profile `{suite['profile']}`; seeds {', '.join(map(str, suite['seeds']))}",
        f"- machine: {'; or '.join(summary['machines'])}; written {summary['finished_at']}",
        f"- command: `{summary['command']}`; records: `{summary['records']}`",
        "- PSNR, SSIM and LPIPS on the validation views at the end of the budget, mean over the "
        "seeds; occupancy against the scene's ground truth where it has one. The tracked column "
        "is the validation PSNR during training (a few views): its best and when, and where the "
        "run ended if not at its best.",
        "",
        "## Mean over scenes",
        "",
        mean_table(summary),
        "",
    ]
    for name, scene in summary["scenes"].items():
        budget = scene["budget_min"]
        parts += [
            f"## {name}",
            "",
            (f"{budget:g} minutes per run" if budget else "the profile's step counts")
            + f"; occupancy reference: {scene['occupancy_reference']}. Trained "
            + "; ".join(scene["trained_on"])
            + ".",
            "",
            scene_table(scene),
            "",
        ]
    path.write_text("\n".join(parts))

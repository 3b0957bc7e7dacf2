"""Where does O lose the cells it misses? A finished LeCO run's O scored against the scene's exact
occupancy under several decision rules: keep thresholds on p(E_e), O's top-1, and each of those
grown by a cell in every direction (a miss that a one-cell dilation recovers is a near miss, not a
structure O never learned).

    python -m bench.occupancy_rules --run RUN [--thresholds 0.9,0.97,0.99,0.999]
        [--field-alphas 0.01] [--dilate 1]

RUN is a `leco train` or `leco bench` run folder of a method with an occupancy network, on a scene
with exact ground truth (the synthetic presets). One row a rule: recall, precision and F1 on the
cells the validation views observe (the paper's protocol, as `leco eval` scores it), the ground's
recall and the recall of each height layer, bottom first. Prints a markdown table; `--json` writes
the rows too.

The last rows score the main field itself: a cell is occupied where the field's density stops at
least `--field-alphas` of the light over one step of the box diagonal / 256 (the alpha nerfacc's
grid keeps a cell by; the `cpu` profile's grid marches 256 steps). Whether the main network holds
the cells O misses says whether labels read off its density over the whole box could teach O
them."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from model.estimators.online import BOX_STEPS

DEFAULT_THRESHOLDS = "0.9,0.97,0.99,0.999"
DEFAULT_FIELD_ALPHAS = "0.01"
# the step of the field rules: the box diagonal over this many, as O's online box points take it
FIELD_STEPS = BOX_STEPS


def occupancy_probability_grid(network, aabb, resolution: int, subdivisions: int = 2):
    """(R, R, R): the largest 1 - p(E_e) over each cell's sub-cell centres, and whether O's top-1
    is a scene expert at any of them. A threshold rule is then one comparison of the first (keep
    where p(E_e) < t at some sub-cell <=> max(1 - p(E_e)) > 1 - t), as the evaluation samples a
    predictor (model/evaluation/occupancy.py `predicted_grid`)."""
    import torch

    from model.evaluation.occupancy import subcell_points

    count = resolution**3
    keep_p = torch.zeros(count)
    top1 = torch.zeros(count, dtype=torch.bool)
    empty = network.empty_index
    with torch.no_grad():
        for points in subcell_points(aabb, resolution, subdivisions):
            for s in range(0, len(points), 1 << 16):
                logits = network(points[s : s + (1 << 16)]).float()
                p = 1.0 - torch.softmax(logits, dim=-1)[:, empty]
                keep_p[s : s + len(p)] = torch.maximum(keep_p[s : s + len(p)], p)
                top1[s : s + len(p)] |= logits.argmax(dim=-1) != empty
    shape = (resolution,) * 3
    return keep_p.reshape(shape), top1.reshape(shape)


def field_density_grid(field, aabb, resolution: int, subdivisions: int = 2):
    """(R, R, R): the main field's largest density over each cell's sub-cell centres (as
    `occupancy_probability_grid` samples O), asked as an occupancy grid's update asks it (no view
    direction, the first image's appearance)."""
    import torch

    from model.evaluation.occupancy import subcell_points
    from model.methods.leco.guided_render import density_at

    sigma = torch.zeros(resolution**3)
    with torch.no_grad():
        for points in subcell_points(aabb, resolution, subdivisions):
            for s in range(0, len(points), 1 << 16):
                value = density_at(field, points[s : s + (1 << 16)]).float().reshape(-1)
                sigma[s : s + len(value)] = torch.maximum(sigma[s : s + len(value)], value)
    return sigma.reshape((resolution,) * 3)


def field_rules(field, aabb, resolution: int, alphas: list[float]) -> dict:
    """{rule name: (R, R, R) bool}: where the field's alpha over one step of diagonal/FIELD_STEPS
    reaches each of `alphas`."""
    import math

    step = float((aabb[1] - aabb[0]).norm()) / FIELD_STEPS
    sigma = field_density_grid(field, aabb, resolution)
    # alpha = 1 - exp(-sigma * step) >= a  <=>  sigma >= -log(1 - a) / step
    return {
        f"field alpha >= {a:g} (step diagonal/{FIELD_STEPS})": sigma >= -math.log1p(-a) / step
        for a in alphas
    }


def dilated(grid, cells: int):
    """A boolean grid grown by `cells` in every direction (a (2c+1)^3 max-pool)."""
    import torch.nn.functional as F

    if cells <= 0:
        return grid
    k = 2 * cells + 1
    pooled = F.max_pool3d(grid[None, None].float(), kernel_size=k, stride=1, padding=cells)
    return pooled[0, 0] > 0


def score_rules(
    run: Path, thresholds: list[float], dilate: int, field_alphas: list[float] | None = None
) -> list[dict]:
    import torch

    from model.evaluation.occupancy import predicted_grid, reference_from_depth, score_grid
    from workers.train.evaluate import OCCUPANCY_RESOLUTION, load_final

    cfg, scene, method, models = load_final(run, torch.device("cpu"))
    predictor = getattr(method, "predictor", None)
    if predictor is None:
        raise SystemExit(f"{run}: the run's method ({cfg.method}) has no occupancy network O")
    if scene.occupancy is None:
        raise SystemExit(f"{run}: the scene has no exact occupancy (a synthetic preset has one)")
    views = scene.splits.get("val", scene.train)
    truth = scene.occupancy
    aabb = truth.aabb.float()
    resolution = OCCUPANCY_RESOLUTION
    reference = predicted_grid(truth.lookup, aabb, resolution)
    _, observed = reference_from_depth(views, aabb, resolution)
    keep_p, top1 = occupancy_probability_grid(predictor.network, aabb, resolution)
    rules = {f"p(E_e) < {t:g}": keep_p > 1.0 - t for t in thresholds}
    rules["top-1 (the paper)"] = top1
    rules.update(field_rules(models.field.eval(), aabb, resolution, field_alphas or []))
    rows = []
    for name, grid in rules.items():
        for cells in sorted({0, dilate}):
            scores = score_grid(dilated(grid, cells), reference, observed)
            rows.append(
                {
                    "rule": name + (f", dilated {cells}" if cells else ""),
                    "recall": scores["recall"],
                    "precision": scores["precision"],
                    "f1": scores["f1"],
                    "ground_recall": scores["ground_recall"],
                    "layers": [layer["recall"] for layer in scores["layers"]],
                    "layer_cells": [layer["reference_cells"] for layer in scores["layers"]],
                }
            )
    return rows


def table(rows: list[dict]) -> str:
    def cell(x) -> str:
        return "-" if x is None else f"{x:.2f}"

    lines = [
        "| rule | recall | precision | F1 | ground | layer recall, bottom first |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        layers = " ".join(cell(x) for x in r["layers"])
        lines.append(
            f"| {r['rule']} | {cell(r['recall'])} | {cell(r['precision'])} | {r['f1']:.3f} | "
            f"{cell(r['ground_recall'])} | {layers} |"
        )
    if rows:
        lines.append(f"\nobserved occupied cells by layer: {rows[0]['layer_cells']}")
    return "\n".join(lines)


def report(rows: list[dict], json_path: str | None) -> int:
    """Print the rows' table and, given a path, write them there as JSON (the exit status, 0)."""
    print(table(rows))
    if json_path:
        Path(json_path).write_text(json.dumps(rows, indent=1))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True, help="a finished run folder")
    parser.add_argument(
        "--thresholds",
        default=DEFAULT_THRESHOLDS,
        help=f"keep thresholds on p(E_e), comma-separated (default {DEFAULT_THRESHOLDS})",
    )
    parser.add_argument(
        "--field-alphas",
        default=DEFAULT_FIELD_ALPHAS,
        help="also the main field as a grid, kept where its alpha over one step reaches each "
        f"(comma-separated, default {DEFAULT_FIELD_ALPHAS}; empty for none)",
    )
    parser.add_argument("--dilate", type=int, default=1, help="also each rule grown by N cells")
    parser.add_argument("--json", default=None, help="also write the rows here")
    args = parser.parse_args(argv)
    try:
        thresholds = [float(t) for t in args.thresholds.split(",") if t.strip()]
        alphas = [float(a) for a in args.field_alphas.split(",") if a.strip()]
    except ValueError:
        parser.error(
            f"--thresholds {args.thresholds!r} / --field-alphas {args.field_alphas!r}: expected "
            "numbers, e.g. 0.9,0.99"
        )
    if any(not 0.0 < t < 1.0 for t in thresholds):
        parser.error(f"--thresholds {args.thresholds!r}: each must lie in (0, 1)")
    if any(not 0.0 < a < 1.0 for a in alphas):
        parser.error(f"--field-alphas {args.field_alphas!r}: each must lie in (0, 1)")
    if args.dilate < 0:
        parser.error("--dilate must be 0 or more")
    try:
        rows = score_rules(Path(args.run), thresholds, args.dilate, alphas)
    except (FileNotFoundError, ValueError) as error:  # no finished run there, or not a run folder
        parser.exit(2, f"occupancy_rules: {error}\n")
    return report(rows, args.json)


if __name__ == "__main__":
    raise SystemExit(main())

"""Can O hold the scene's occupancy at all? O as a method's profile builds it, fitted straight to
the scene's exact occupancy at the very points the evaluation samples, then scored as a finished
run's O is (model/evaluation/occupancy.py). If O misses the top height layers even then, no training
label will teach them and the lever is O's size; if it keeps them, what O lacks in a run is the
labels.

    python -m bench.occupancy_capacity --scene SCENE [--method ngp-leco] [--profile cpu]
        [--steps 3000] [--set KEY=VALUE ...] [--json OUT]

SCENE is a synthetic preset's folder (it ships exact occupancy). Each step draws a batch of the
evaluation grid's sub-cell centres (half uniformly, half from occupied ones, so the few top cells
are seen) and pushes O's decision logit (the sampler's rule: keep where p(E_e) < the method's
`guided.empty_threshold`) towards the truth with a binary cross-entropy. Prints one markdown row
(recall, precision, F1, ground recall, recall by layer) at each checkpoint."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

CHECKPOINTS = 4  # rows printed over the fit


def fit(network, points, labels, steps: int, batch: int, lr: float, threshold, seed: int, report):
    """Adam on O's decision logit at `points` (N, 3) against `labels` (N,) bool; `report(step)`
    at CHECKPOINTS evenly spaced steps."""
    import torch
    import torch.nn.functional as F

    generator = torch.Generator().manual_seed(seed)
    occupied = torch.nonzero(labels)[:, 0]
    optimizer = torch.optim.Adam(network.parameters(), lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, steps)
    marks = {round(steps * (i + 1) / CHECKPOINTS) for i in range(CHECKPOINTS)}
    for step in range(1, steps + 1):
        uniform = torch.randint(len(points), (batch // 2,), generator=generator)
        positive = occupied[
            torch.randint(len(occupied), (batch - batch // 2,), generator=generator)
        ]
        rows = torch.cat([uniform, positive])
        logit = network.decision_logit(network(points[rows]), threshold)
        loss = F.binary_cross_entropy_with_logits(logit, labels[rows].float())
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        schedule.step()
        if step in marks:
            report(step)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", required=True, help="a synthetic preset's scene folder")
    parser.add_argument("--method", default="ngp-leco", help="whose O (default ngp-leco)")
    parser.add_argument("--profile", default="cpu")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--batch", type=int, default=8192)
    parser.add_argument("--lr", type=float, default=2e-3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--json", default=None, help="also write the rows here")
    args = parser.parse_args(argv)
    if args.steps < CHECKPOINTS or args.batch < 2:
        parser.error(f"--steps must be at least {CHECKPOINTS} and --batch at least 2")

    import torch

    from bench.occupancy_rules import report, table
    from model.evaluation.occupancy import (
        predicted_grid,
        reference_from_depth,
        score_grid,
        subcell_points,
    )
    from model.methods.leco.method import hmoe
    from model.scenes import load_scene
    from workers.config import TrainConfig, parse_overrides
    from workers.train.evaluate import OCCUPANCY_RESOLUTION

    torch.manual_seed(args.seed)
    scene = load_scene(Path(args.scene))
    if scene.occupancy is None:
        parser.exit(2, f"occupancy_capacity: {args.scene} has no exact occupancy\n")
    config = TrainConfig(
        method=args.method, profile=args.profile, overrides=parse_overrides(args.set)
    )
    profile = config.resolved_profile()
    network = hmoe(profile, len(scene.train)).gate
    threshold = profile.guided.empty_threshold
    truth, views = scene.occupancy, scene.splits.get("val", scene.train)
    aabb, resolution = truth.aabb.float(), OCCUPANCY_RESOLUTION
    points = torch.cat(list(subcell_points(aabb, resolution)))
    labels = truth.lookup(points)
    reference = predicted_grid(truth.lookup, aabb, resolution)
    _, observed = reference_from_depth(views, aabb, resolution)
    rows: list[dict] = []
    started = time.perf_counter()

    def checkpoint(step: int) -> None:
        with torch.no_grad():
            grid = predicted_grid(lambda p: network.occupied(p, threshold), aabb, resolution)
        scores = score_grid(grid, reference, observed)
        rows.append(
            {
                "rule": f"step {step} ({time.perf_counter() - started:.0f} s)",
                **{k: scores[k] for k in ("recall", "precision", "f1", "ground_recall")},
                "layers": [layer["recall"] for layer in scores["layers"]],
                "layer_cells": [layer["reference_cells"] for layer in scores["layers"]],
            }
        )
        print(table(rows[-1:]).splitlines()[2], flush=True)

    count = sum(p.numel() for p in network.parameters())
    print(
        f"O of {args.method} ({args.profile}, {' '.join(args.set) or 'defaults'}): "
        f"{count:,} parameters, keep where p(E_e) < {threshold}"
    )
    fit(network, points, labels, args.steps, args.batch, args.lr, threshold, args.seed, checkpoint)
    return report(rows, args.json)


if __name__ == "__main__":
    raise SystemExit(main())

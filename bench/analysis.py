"""Numbers derived from the runs: time to reach a PSNR, speed-ups, per-variant means over seeds,
targets."""

from __future__ import annotations

import math
import statistics

from model.methods import METHODS, family_of, with_role


def roles(runs: list[dict] | None = None) -> tuple[str | None, str | None]:
    """(the method speed-ups are reported for, the unguided reference they are measured against):
    the pair of the family the runs compare (Switch-NeRF's, or the hash grids'), or the first
    registered pair when no compared run has one."""
    names = {r["variant"] for r in runs or [] if not r["ablation"]}
    ours, ref = with_role("ours", names), with_role("reference", names)
    return ours or with_role("ours"), ref or with_role("reference")


def families(runs: list[dict]) -> list[tuple[str, str | None]]:
    """(ours, reference) of every family whose "ours" the runs compare, in registry order. A
    benchmark of two families judges each "ours" against its own family only: S+Ours against
    NGP+Ours is a comparison of main networks, not of samplers."""
    names = {r["variant"] for r in runs if not r["ablation"]}
    out = []
    for ours in [n for n, m in METHODS.items() if m.role == "ours" and n in names]:
        out.append((ours, with_role("reference", names & set(family_of(ours)))))
    return out


def in_family(runs: list[dict], ours: str) -> list[dict]:
    """The runs of `ours`'s family (its ablations and rungs included)."""
    family = set(family_of(ours))
    return [r for r in runs if r["method"] in family]


def family_block(runs: list[dict], ours: str | None) -> dict:
    """`ours` against the other methods of its family (all the runs when None): equal PSNR,
    speed-ups and targets."""
    group = runs if ours is None else in_family(runs, ours)
    equal = equal_psnr(group)
    speed = speedups(group, equal)
    ours, ref = roles(group)
    return {
        "ours": ours,
        "reference": ref,
        "equal_psnr": equal,
        "speedups": speed,
        "targets": targets(group, speed),
    }


def main_curve(run: dict) -> list[tuple[float, float]]:
    """(training seconds, validation PSNR) of the main network; LeCO's times include its occupancy
    phase."""
    return [
        (p["wall_time_s"], p["val_psnr"])
        for p in run["curve"]
        if p.get("phase") == "main" and "val_psnr" in p
    ]


def time_to_psnr(points: list[tuple[float, float]], target: float) -> float | None:
    """First training time at which the curve reaches `target`, linearly interpolated between
    evaluations."""
    previous = None
    for t, value in points:
        if value >= target:
            if previous is None or previous[1] >= target:
                return t
            (t0, v0) = previous
            return t0 + (target - v0) / (value - v0) * (t - t0)
        previous = (t, value)
    return None


TRACKED_STEPS = (1000, 2000, 4000, 8000)  # main steps the tracked curve is read at


def psnr_at_main_step(run: dict, step: int) -> float | None:
    """The tracked validation PSNR at main-phase step `step`, linearly interpolated between the
    evaluations around it; None before the first or after the last (a run that never got there)."""
    points = [
        (p["phase_step"], p["val_psnr"])
        for p in run["curve"]
        if p.get("phase") == "main" and "val_psnr" in p and "phase_step" in p
    ]
    for (s0, v0), (s1, v1) in zip(points, points[1:]):
        if s0 <= step <= s1:
            return v0 if s1 == s0 else v0 + (step - s0) / (s1 - s0) * (v1 - v0)
    return None


def tracked_by_step(runs: list[dict]) -> dict[str, dict[int, tuple[float | None, float | None]]]:
    """Per variant, the tracked PSNR at each of TRACKED_STEPS (mean and std over seeds; a seed that
    did not get there is left out)."""
    names = dict.fromkeys(r["variant"] for r in runs)
    return {
        n: {
            step: mean_std([psnr_at_main_step(r, step) for r in runs if r["variant"] == n])
            for step in TRACKED_STEPS
        }
        for n in names
    }


def mean_std(values: list[float | None]) -> tuple[float | None, float | None]:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    if not finite:
        return None, None
    return statistics.fmean(finite), (statistics.stdev(finite) if len(finite) > 1 else None)


def get(summary: dict, path: str):
    node = summary
    for part in path.split("."):
        if not isinstance(node, dict) or node.get(part) is None:
            return None
        node = node[part]
    return node


def per_variant(runs: list[dict], path: str) -> dict[str, tuple[float | None, float | None]]:
    names = dict.fromkeys(r["variant"] for r in runs)
    return {
        n: mean_std([get(r["summary"], path) for r in runs if r["variant"] == n]) for n in names
    }


def layer_recalls(runs: list[dict]) -> dict[str, list[dict]]:
    """Per variant with an occupancy scored by height layer: each layer's z range, reference cells
    and recall (mean and std over seeds; None where no seed had reference cells there). Summaries
    without layers: left out."""
    out: dict[str, list[dict]] = {}
    for name in dict.fromkeys(r["variant"] for r in runs):
        scored = [get(r["summary"], "occupancy.layers") for r in runs if r["variant"] == name]
        scored = [layers for layers in scored if layers]
        if not scored:
            continue
        rows = []
        for i, layer in enumerate(scored[0]):
            mean, std = mean_std([layers[i]["recall"] for layers in scored])
            rows.append(
                {
                    "z_min": layer["z_min"],
                    "z_max": layer["z_max"],
                    "reference_cells": layer["reference_cells"],
                    "recall": mean,
                    "recall_std": std,
                }
            )
        out[name] = rows
    return out


def measured_or_blank(
    runs: list[dict], name: str, path: str, parent: str
) -> tuple[float | None, float | None] | str:
    """A figure's mean over the variant's seeds; where none has it, "–" when the runs measured
    `parent` (the figure does not apply to this method, e.g. the fallback share of a method without
    one) and "n/a" when they did not (a summary written before the figure existed)."""
    value = mean_std([get(r["summary"], path) for r in runs if r["variant"] == name])
    if value[0] is not None:
        return value
    return (
        "–"
        if any(get(r["summary"], parent) is not None for r in runs if r["variant"] == name)
        else "n/a"
    )


def equal_psnr(runs: list[dict]) -> list[dict]:
    """Per seed: the best validation PSNR every compared method reached, and when each reached
    it."""
    out = []
    main = [r for r in runs if not r["ablation"]]
    for seed in sorted({r["seed"] for r in main}):
        group = [r for r in main if r["seed"] == seed and main_curve(r)]
        if len(group) < 2:
            continue
        target = min(max(v for _, v in main_curve(r)) for r in group)
        out.append(
            {
                "seed": seed,
                "target_psnr": target,
                "time_s": {r["variant"]: time_to_psnr(main_curve(r), target) for r in group},
            }
        )
    return out


def to_baseline_best(runs: list[dict], base: str) -> list[float | None]:
    """Per seed: the baseline's time to its own best validation PSNR over LeCO's time to that PSNR
    (None where LeCO never reached it). The issue's "vanilla's final PSNR in half its time" is this
    at >= 2."""
    out, ours = [], roles(runs)[0]
    main = [r for r in runs if not r["ablation"]]
    for seed in sorted({r["seed"] for r in main}):
        curves = {r["variant"]: main_curve(r) for r in main if r["seed"] == seed}
        if not curves.get(base) or not curves.get(ours):
            continue
        target = max(v for _, v in curves[base])
        out.append(ratio(time_to_psnr(curves[base], target), time_to_psnr(curves[ours], target)))
    return out


def ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a is not None and b not in (None, 0) else None


def speedups(runs: list[dict], equal: list[dict]) -> dict[str, dict]:
    """LeCO over each baseline: rays/s, time to equal PSNR (mean over seeds), samples per ray,
    memory."""
    names = list(dict.fromkeys(r["variant"] for r in runs if not r["ablation"]))
    ours = roles(runs)[0]
    if ours is None or ours not in names:
        return {}
    rays = per_variant(runs, "rays_per_s")
    spr = per_variant(runs, "samples_per_ray")
    act = per_variant(runs, "activation_memory_mb")
    peak = per_variant(runs, "peak_memory_mb")
    out = {}
    for base in [n for n in names if n != ours]:
        times = [ratio(e["time_s"].get(base), e["time_s"].get(ours)) for e in equal]
        best = to_baseline_best(runs, base)
        out[base] = {
            "rays_per_s": ratio(rays[ours][0], rays[base][0]),
            "time_to_equal_psnr": mean_std(times)[0],
            "time_to_its_best_psnr": None if None in best else mean_std(best)[0],
            "time_to_its_best_psnr_per_seed": best,
            "samples_per_ray_fraction": ratio(spr[ours][0], spr[base][0]),
            "activation_memory_fraction": ratio(act[ours][0], act[base][0]),
            "peak_memory_fraction": ratio(peak[ours][0], peak[base][0]),
        }
    return out


def _at_least(a: float | None, b: float | None) -> bool | None:
    return None if a is None or b is None else a >= b


def _above(a: float | None, b: float | None) -> bool | None:
    return None if a is None or b is None else a > b


def targets(runs: list[dict], speed: dict) -> list[dict]:
    """The issue's targets, each with what was measured and whether it was met (None: not measurable
    here): against the reference method, then against every baseline that learns an occupancy."""
    names = {r["variant"] for r in runs if not r["ablation"]}
    ours, ref = roles(runs)
    psnr = per_variant(runs, "val.psnr")
    f1 = per_variant(runs, "occupancy.f1")
    params = per_variant(runs, "occupancy.params")
    occ_ratio = per_variant(runs, "occupancy.occupancy_ratio")
    rows = []

    def add(text: str, measured: str, met: bool | None) -> None:
        rows.append({"target": text, "measured": measured, "met": met})

    fmt = lambda v, spec: "n/a" if v is None else format(v, spec)
    if ours is not None and ref is not None and {ours, ref} <= names:
        s, goal, label = speed[ref], METHODS[ref].reference_targets, METHODS[ref].label
        if goal.rays_per_s is not None:
            add(
                f"guided phase rays/s >= {goal.rays_per_s:g}x {label}'s",
                f"{fmt(s['rays_per_s'], '.2f')}x",
                None if s["rays_per_s"] is None else s["rays_per_s"] >= goal.rays_per_s,
            )
        best, k = s["time_to_its_best_psnr_per_seed"], goal.best_sooner
        add(
            f"reaches the best PSNR of {label} in at most half of its time (per seed)"
            if k == 2
            else f"reaches the best PSNR of {label} {'sooner' if k == 1 else f'{k:g}x sooner'} "
            "(per seed)",
            ", ".join("never" if b is None else f"{b:.2f}x" for b in best) or "n/a",
            None if not best else all(b is not None and b >= k for b in best),
        )
        if goal.samples_fraction is not None:
            add(
                f"main-network samples per ray <= {goal.samples_fraction:.0%} of {label}",
                f"{fmt(s['samples_per_ray_fraction'], '.1%')}",
                None
                if s["samples_per_ray_fraction"] is None
                else s["samples_per_ray_fraction"] <= goal.samples_fraction,
            )
        add(
            f"validation PSNR >= {label}'s at equal budget",
            f"{fmt(psnr[ours][0], '.2f')} vs {fmt(psnr[ref][0], '.2f')} dB",
            _at_least(psnr[ours][0], psnr[ref][0]),
        )
        if goal.memory_fraction is not None:
            memory = s["peak_memory_fraction"] if _on_gpu(runs) else s["activation_memory_fraction"]
            add(
                f"peak training memory <= {goal.memory_fraction:.0%} of {label}'s"
                + ("" if _on_gpu(runs) else " (autograd activations, CPU)"),
                f"{fmt(memory, '.1%')} of {label}'s",
                None if memory is None else memory <= goal.memory_fraction,
            )
    if ours is None or ours not in names:
        return rows
    for other in [n for n in METHODS if n in names and n != ours and METHODS[n].has_occupancy]:
        label = METHODS[other].label
        if other != ref:  # the reference's row is above
            add(
                f"validation PSNR >= {label}'s at equal budget",
                f"{fmt(psnr[ours][0], '.2f')} vs {fmt(psnr[other][0], '.2f')} dB",
                _at_least(psnr[ours][0], psnr[other][0]),
            )
        add(
            f"occupancy F1 above {label}'s",
            f"{fmt(f1[ours][0], '.3f')} vs {fmt(f1[other][0], '.3f')}",
            _above(f1[ours][0], f1[other][0]),
        )
        bound = METHODS[other].occupancy_size_target
        if bound is not None:
            p = ratio(params[ours][0], params[other][0])
            add(
                f"occupancy parameters <= {bound:.0%} of {label}'s",
                f"{fmt(p, '.1%')}",
                None if p is None else p <= bound,
            )
    r = occ_ratio[ours][0]
    add("LeCO occupancy ratio <= 20%", fmt(r, ".1%"), None if r is None else r <= 0.20)
    return rows


def _on_gpu(runs: list[dict]) -> bool:
    return any(r["summary"]["config"].get("use_gpu") for r in runs)

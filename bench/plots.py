"""The report's figures as PNG (matplotlib, Agg): PSNR against training time (Fig. 9), occupancy F1
and empty-expert fraction against occupancy-phase step (Fig. 5), main-network samples per ray,
occupancy recall by height layer, the occupancy point clouds of LeCO and the grid side by side (Fig.
7) and validation renders side by side (Fig. 8)."""

from __future__ import annotations

from pathlib import Path

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

from bench.analysis import layer_recalls, main_curve, per_variant  # noqa: E402
from model.methods import METHODS  # noqa: E402

# Each method's colour is its own (Method.colour); the ablations' are these; anything else:
# matplotlib's cycle.
COLOURS = {
    "leco-homogeneous": "#9467bd",
    "leco-no-density-loss": "#ff7f0e",
    **{name: m.colour for name, m in METHODS.items() if m.colour},
}


def _save(fig, path: Path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name


def psnr_vs_time(runs: list[dict], path: Path) -> str:
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for run in runs:
        points = main_curve(run)
        if points:
            t, v = zip(*points)
            ax.plot(
                np.array(t) / 60,
                v,
                marker=".",
                color=COLOURS.get(run["variant"]),
                alpha=1.0 if run["seed"] == runs[0]["seed"] else 0.5,
                label=f"{run['label']} (seed {run['seed']})",
            )
    ax.set_xlabel("training time (min; LeCO includes its occupancy phase)")
    ax.set_ylabel("validation PSNR (dB)")
    ax.set_title("PSNR against training time (paper Fig. 9)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return _save(fig, path)


def occupancy_phase(runs: list[dict], path: Path) -> str | None:
    leco = [r for r in runs if len(METHODS[r["method"]].phases) > 1]  # runs with an occupancy phase
    if not leco:
        return None
    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.6))
    for run in leco:
        rows = [p for p in run["curve"] if p.get("phase") == "occupancy"]
        label = f"{run['label']} (seed {run['seed']})"
        f1 = [(p["phase_step"], p["occupancy_f1"]) for p in rows if "occupancy_f1" in p]
        if f1:
            left.plot(*zip(*f1), marker=".", color=COLOURS.get(run["variant"]), label=label)
        empty = [
            (p["phase_step"], 100 * p["fraction_empty"]) for p in rows if "fraction_empty" in p
        ]
        if empty:
            right.plot(*zip(*empty), color=COLOURS.get(run["variant"]), label=label)
    left.set(
        xlabel="occupancy-phase step", ylabel="occupancy F1", title="Occupancy F1 (paper Fig. 5)"
    )
    right.set(
        xlabel="occupancy-phase step",
        ylabel="% of points sent to E_e",
        title="Empty-expert fraction",
    )
    if not left.lines:  # no reference to score against while training (e.g. lego)
        left.text(
            0.5,
            0.5,
            "no occupancy reference\nduring training",
            ha="center",
            va="center",
            transform=left.transAxes,
        )
    for ax in (left, right):
        ax.grid(alpha=0.3)
        if ax.lines:
            ax.legend(fontsize=7)
    return _save(fig, path)


def samples_per_ray(runs: list[dict], path: Path) -> str:
    means = per_variant(runs, "samples_per_ray")
    measured = {n: m for n, (m, _) in means.items() if m is not None}
    names = list(measured)
    fig, ax = plt.subplots(figsize=(6, 3.4))
    bars = ax.bar(names, list(measured.values()), color=[COLOURS.get(n, "grey") for n in names])
    ax.bar_label(bars, fmt="%.1f")
    ax.set_ylabel("main-network samples per ray")
    ax.set_title("Main-network samples per ray (mean over the main phase)")
    return _save(fig, path)


def recall_by_layer(runs: list[dict], path: Path) -> str | None:
    """Each method's occupancy recall per height layer, height upwards (world z is up), the ground's
    in the legend: a sampler that drops the ground or the roofs shows as a dent at that height."""
    layers = layer_recalls(runs)
    if not layers:
        return None
    ground = per_variant(runs, "occupancy.ground_recall")
    labels = {r["variant"]: r["label"] for r in runs}
    fig, ax = plt.subplots(figsize=(6, 4.2))
    for name, rows in layers.items():
        shown = [
            (r["recall"], 0.5 * (r["z_min"] + r["z_max"])) for r in rows if r["recall"] is not None
        ]
        if not shown:
            continue
        g = ground[name][0]
        ax.plot(
            *zip(*shown),
            marker="o",
            color=COLOURS.get(name),
            label=f"{labels[name]} (ground {'n/a' if g is None else f'{g:.2f}'})",
        )
    ax.set(
        xlim=(-0.02, 1.02),
        ylim=(0, 1),
        xlabel="recall of occupied, observed cells",
        ylabel="height in the box (z, 0 = bottom)",
        title="Occupancy recall by height layer",
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return _save(fig, path)


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    rows = np.frombuffer(data[end:], dtype=np.dtype([("xyz", "<f4", 3), ("rgba", "u1", 4)]))
    return rows["xyz"], rows["rgba"]


def occupancy_clouds(runs: list[dict], path: Path) -> str | None:
    """Top-down and oblique views of each method's occupied points (coloured by the main
    network)."""
    chosen = [
        r
        for r in runs
        if METHODS[r["method"]].has_occupancy
        and not r["ablation"]
        and (Path(r["run_dir"]) / "occupancy.ply").exists()
        and r["seed"] == runs[0]["seed"]
    ]
    if not chosen:
        return None
    fig, axes = plt.subplots(2, len(chosen), figsize=(4.5 * len(chosen), 8), squeeze=False)
    for col, run in enumerate(chosen):
        xyz, rgba = read_ply(Path(run["run_dir"]) / "occupancy.ply")
        colours = rgba[:, :3] / 255.0
        top, oblique = axes[0, col], axes[1, col]
        order = np.argsort(xyz[:, 2])  # higher points drawn last, as seen from above
        top.scatter(xyz[order, 0], xyz[order, 1], c=colours[order], s=0.5, linewidths=0)
        top.set_title(f"{run['label']}: {len(xyz):,} points, from above", fontsize=9)
        depth = xyz[:, 0] + xyz[:, 1]
        order = np.argsort(-depth)
        oblique.scatter(
            xyz[order, 0] - xyz[order, 1],
            xyz[order, 2] + 0.3 * depth[order],
            c=colours[order],
            s=0.5,
            linewidths=0,
        )
        oblique.set_title("oblique", fontsize=9)
        for ax in (top, oblique):
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
    fig.suptitle("Occupied points kept for the main network (paper Fig. 7)")
    return _save(fig, path)


def render_grid(runs: list[dict], path: Path) -> str | None:
    """Each method's first final validation render (prediction | truth | depth), one row per
    method."""
    rows = []
    for run in runs:
        if run["seed"] != runs[0]["seed"]:
            continue
        renders = sorted((Path(run["run_dir"]) / "renders").glob("final_*.png"))
        if renders:
            rows.append((run["label"], Image.open(renders[0]).convert("RGB")))
    if not rows:
        return None
    fig, axes = plt.subplots(len(rows), 1, figsize=(9, 2.6 * len(rows)), squeeze=False)
    for ax, (label, image) in zip(axes[:, 0], rows):
        ax.imshow(np.asarray(image))
        ax.set_title(f"{label}: prediction | ground truth | depth", fontsize=9)
        ax.axis("off")
    fig.suptitle("Validation renders (paper Fig. 8)")
    return _save(fig, path)


def sweep_points(runs: list[dict]) -> dict[str, list[dict]]:
    """Per method, its default run and its `--sweep` runs (first seed), ordered by samples per
    ray."""
    seed = runs[0]["seed"] if runs else None
    out: dict[str, list[dict]] = {}
    for r in runs:
        if r["seed"] == seed and (r.get("sweep") or r["variant"] == r["method"]):
            out.setdefault(r["method"], []).append(r)
    return {
        m: sorted(rs, key=lambda r: r["summary"].get("samples_per_ray") or 0)
        for m, rs in out.items()
        if any(r.get("sweep") for r in rs)
    }


def speed_vs_error(runs: list[dict], path: Path) -> str | None:
    """Final PSNR against main-network samples per ray and against rays/s: each method's Pareto
    curve."""
    points = sweep_points(runs)
    if not points:
        return None
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for method, rs in points.items():
        psnr = [r["summary"]["val"]["psnr"] for r in rs]
        for ax, key in zip(axes, ("samples_per_ray", "rays_per_s")):
            x = [r["summary"].get(key) for r in rs]
            ax.plot(
                x, psnr, marker="o", color=COLOURS.get(method), label=rs[0]["label"].split(",")[0]
            )
            for xi, yi, r in zip(x, psnr, rs):
                ax.annotate(
                    r["label"].split(", ", 1)[1] if r.get("sweep") else "default",
                    (xi, yi),
                    fontsize=6,
                    textcoords="offset points",
                    xytext=(3, 3),
                )
    axes[0].set(
        xscale="log",
        xlabel="main-network samples per ray (log)",
        ylabel="final validation PSNR (dB)",
        title="PSNR against samples per ray",
    )
    axes[1].set(xscale="log", xlabel="rays/s of the main phase (log)", title="PSNR against speed")
    for ax in axes:
        # Ticks at the measured points, in plain numbers: a log axis's default labels collide at
        # this range.
        ticks = sorted({round(x) for line in ax.get_lines() for x in line.get_xdata() if x})
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xticks(ticks, [f"{t:,}" for t in ticks], rotation=45, fontsize=7)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    return _save(fig, path)


def sweep_curves(runs: list[dict], path: Path) -> str | None:
    """PSNR against training time for every sweep point, one panel per method."""
    points = sweep_points(runs)
    if not points:
        return None
    fig, axes = plt.subplots(1, len(points), figsize=(4.6 * len(points), 3.8), squeeze=False)
    for ax, rs in zip(axes[0], points.values()):
        for r in rs:
            curve = main_curve(r)
            if curve:
                t, v = zip(*curve)
                ax.plot(
                    np.array(t) / 60,
                    v,
                    marker=".",
                    label=r["label"].split(", ", 1)[1] if r.get("sweep") else "default",
                    alpha=1.0 if not r.get("sweep") else 0.7,
                )
        ax.set(
            xlabel="training time (min)",
            ylabel="validation PSNR (dB)",
            title=rs[0]["label"].split(",")[0],
        )
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    return _save(fig, path)


def all_figures(runs: list[dict], out: Path) -> dict[str, str]:
    out.mkdir(parents=True, exist_ok=True)
    main = [r for r in runs if not r["ablation"]]
    figures = {
        "psnr_vs_time": psnr_vs_time(main or runs, out / "psnr_vs_time.png"),
        "occupancy_phase": occupancy_phase(runs, out / "occupancy_phase.png"),
        "samples_per_ray": samples_per_ray(runs, out / "samples_per_ray.png"),
        "recall_by_layer": recall_by_layer(main or runs, out / "recall_by_layer.png"),
        "occupancy_clouds": occupancy_clouds(runs, out / "occupancy_leco_vs_grid.png"),
        "renders": render_grid(runs, out / "renders.png"),
        "speed_vs_error": speed_vs_error(runs, out / "speed_vs_error.png"),
        "sweep_psnr_vs_time": sweep_curves(runs, out / "sweep_psnr_vs_time.png"),
    }
    return {k: f"figures/{v}" for k, v in figures.items() if v}

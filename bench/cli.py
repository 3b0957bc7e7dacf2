"""`leco bench`: train LeCO, vanilla Switch-NeRF and the occupancy grid on one scene at the same
profile, seed and wall-clock budget, then write results.json, report.md and figures/ (see
docs/BENCHMARKS.md)."""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

from pydantic import ValidationError


def bench_command(args: argparse.Namespace) -> int:
    if args.suite:
        return suite_command(args)
    if not args.scene:
        raise SystemExit("leco bench: name a scene (--scene DIR) or a suite (--suite NAME)")
    for flag, value in (
        ("--scenes", args.scenes),
        ("--commit", args.commit),
        ("--records", args.records),
    ):
        if value:
            raise SystemExit(f"leco bench: {flag} goes with --suite; with --scene, drop it")
    from model.methods import family_of, with_role

    if args.methods is None:
        args.methods = ",".join(family_of(with_role("ours")))
    if args.seeds is None:
        args.seeds = "0"
    from bench import analysis, plots, report
    from bench.runner import BenchError, Plan, config_for, run_variant
    from bench.variants import select
    from model.methods import METHODS, with_role
    from model.scenes import load_scene
    from workers.config import TrainConfig, parse_overrides

    log = lambda text: print(text, file=sys.stderr, flush=True)
    try:
        seeds = parse_seeds(args.seeds)
        overrides = parse_overrides(args.set or [])
        # The sweep's points are relative to the profile each method's run trains, --set included.
        swept = None
        if args.sweep:
            swept = lambda method: TrainConfig(
                method=method, profile=args.profile, overrides=overrides
            ).resolved_profile()
        variants = select(
            [m.strip() for m in args.methods.split(",") if m.strip()],
            args.ablation,
            args.ladder,
            swept,
        )
    except (ValueError, ValidationError) as error:
        raise SystemExit(f"leco bench: {error}") from None
    scene_dir, out = Path(args.scene), Path(args.out)
    # a broken scene fails here, naming what is wrong
    scene = load_scene(scene_dir, downscale=args.downscale)
    every = args.eval_every_s or (args.budget_min * 60 / 15 if args.budget_min else 30.0)
    plan = Plan(
        scene=scene_dir,
        profile=args.profile,
        out=out,
        budget_min=args.budget_min,
        seeds=seeds,
        eval_every_s=every,
        eval_views=args.eval_views,
        backend=args.backend,
        workers=args.workers,
        use_gpu=args.gpu,
        overrides=overrides,
        downscale=args.downscale,
    )
    try:
        for variant in variants:  # every config is valid before the first run starts
            config_for(variant, plan, seeds[0])
    except ValidationError as error:
        problems = "; ".join(
            f"{'.'.join(map(str, e['loc'])) or 'config'}: {e['msg'].removeprefix('Value error, ')}"
            for e in error.errors()
        )
        raise SystemExit(f"leco bench: {problems}") from None
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    try:
        runs = [run_variant(v, plan, seed, log) for seed in seeds for v in variants]
    except BenchError as error:
        raise SystemExit(f"leco bench: {error}") from None

    reference = (
        "none (the scene has no ground truth or depth maps, and no vanilla run to take depth from)"
    )
    if scene.occupancy is not None:
        reference = "exact ground truth (gt/), on the cells the validation views observe"
    elif any(v.depth is not None for v in scene.splits.values()):
        reference = "the scene's depth maps of the validation views"
    else:
        from bench.reference import against_vanilla

        for seed in seeds:
            switch = [
                r for r in runs if r["variant"] == with_role("reference") and r["seed"] == seed
            ]
            same_seed = [r for r in runs if r["seed"] == seed]
            scored = [r for r in same_seed if METHODS[r["method"]].has_occupancy]
            if switch:
                log(
                    f"[bench] seed {seed}: occupancy and surfaces against the trained vanilla "
                    "model's depth"
                )
                found = against_vanilla(
                    Path(switch[0]["run_dir"]),
                    [Path(r["run_dir"]) for r in scored],
                    [Path(r["run_dir"]) for r in same_seed],
                )
                for r in scored:
                    r["summary"]["occupancy"] = {
                        **(r["summary"].get("occupancy") or {}),
                        **found["occupancy"][r["run_dir"]],
                    }
                for r in same_seed:
                    r["summary"]["rays"] = found["rays"][r["run_dir"]]
                reference = (
                    "depth maps of the validation views rendered by the trained vanilla Switch-NeRF"
                )

    families = [analysis.family_block(runs, ours) for ours, _ in analysis.families(runs)]
    first = families[0] if families else analysis.family_block(runs, None)
    results = {
        "plan": {
            "scene": str(scene_dir),
            "profile": args.profile,
            "budget_min": args.budget_min,
            "seeds": seeds,
            "methods": [v.name for v in variants],
            "eval_every_s": every,
            "eval_views": args.eval_views,
            "backend": args.backend,
            "workers": args.workers,
            "gpu": args.gpu,
            "overrides": overrides,
            # the factor the runs trained and were scored at (the scene's own when none was asked
            # for)
            "downscale": scene.downscale,
            "downscale_asked": args.downscale,
        },
        "command": command_line(args),
        "machine": report.machine(),
        "finished_at": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "bench_wall_s": time.perf_counter() - started,
        "occupancy_reference": reference,
        "runs": runs,
        # the first family's comparison at the top level; each family's in `families`
        "equal_psnr": first["equal_psnr"],
        "speedups": first["speedups"],
        "targets": first["targets"],
        "families": families,
    }
    results["figures"] = plots.all_figures(runs, out / "figures")
    report.write_results(results, out)
    report.write_report(results, out)
    log(f"[bench] {report.summary_line(results)}")
    print(f"{out / 'report.md'}\n{out / 'results.json'}")
    return 0


def suite_command(args: argparse.Namespace) -> int:
    """`leco bench --suite NAME`: a suite's scenes from a frozen copy of HEAD (bench/suite.py)."""
    from bench.suite import load_suite, narrowed, run_suite
    from model.errors import LecoError

    log = lambda text: print(text, file=sys.stderr, flush=True)
    conflicting = [
        flag
        for flag, value in (
            ("--scene", args.scene),
            ("--ablation", args.ablation),
            ("--ladder", args.ladder),
            ("--sweep", args.sweep),
            ("--budget-min", args.budget_min),
            ("--eval-every-s", args.eval_every_s),
            ("--downscale", args.downscale),
            ("--gpu", args.gpu),
            ("--backend ray", args.backend != "local"),
        )
        if value
    ]
    if conflicting:
        raise SystemExit(
            f"leco bench --suite: {', '.join(conflicting)} cannot be given with a suite (its file "
            "names the scenes, budgets and evaluation)"
        )
    try:
        suite = narrowed(
            load_suite(args.suite),
            None if args.methods is None else [m for m in args.methods.split(",") if m.strip()],
            None if args.seeds is None else parse_seeds(args.seeds),
            [s.strip() for s in args.scenes.split(",") if s.strip()] if args.scenes else None,
        )
        summary = run_suite(
            suite,
            Path(args.out),
            args.set or [],
            suite_command_line(args),
            log,
            rev=args.commit or "HEAD",
            records=Path(args.records) if args.records else None,
        )
    except ValueError as error:
        raise SystemExit(f"leco bench: {error}") from None
    except LecoError as error:
        raise SystemExit(f"leco bench --suite: {error}") from None
    best = max(summary["methods"].values(), key=lambda m: m["mean_psnr"] or float("-inf"))
    log(f"[suite] {suite.name}: best mean PSNR {best['label']} {best['mean_psnr']}")
    print(f"{Path(args.out) / 'report.md'}\n{Path(args.out) / 'suite.json'}")
    return 0


def suite_command_line(args: argparse.Namespace) -> str:
    words = ["leco", "bench", "--suite", args.suite, "--out", args.out]
    for flag, value in (
        ("--methods", args.methods),
        ("--seeds", args.seeds),
        ("--scenes", args.scenes),
        ("--commit", args.commit),
        ("--records", args.records),
    ):
        if value:
            words += [flag, value]
    for item in args.set or []:
        words += ["--set", item]
    return " ".join(shlex.quote(w) for w in words)


def parse_seeds(text: str) -> list[int]:
    try:
        seeds = [int(s) for s in text.split(",")]
    except ValueError:
        raise ValueError(
            f"--seeds {text!r}: expected comma-separated non-negative integers, e.g. 0,1,2"
        ) from None
    if any(s < 0 for s in seeds):
        raise ValueError(f"--seeds {text!r}: seeds must be non-negative")
    return seeds


def command_line(args: argparse.Namespace) -> str:
    """The invocation, rebuilt from the parsed arguments (so it is exact however the command was
    called)."""
    words = [
        "leco",
        "bench",
        "--scene",
        args.scene,
        "--profile",
        args.profile,
        "--out",
        args.out,
        "--methods",
        args.methods,
        "--seeds",
        args.seeds,
        "--eval-views",
        str(args.eval_views),
    ]
    for flag, value in (
        ("--budget-min", args.budget_min),
        ("--eval-every-s", args.eval_every_s),
        ("--downscale", args.downscale),
    ):
        if value is not None:
            words += [flag, str(value)]
    if args.backend != "local":
        words += ["--backend", args.backend, "--workers", str(args.workers)]
    words += ["--ablation"] * args.ablation + ["--ladder"] * args.ladder + ["--sweep"] * args.sweep
    words += ["--gpu"] * args.gpu
    for item in args.set or []:
        words += ["--set", item]
    return " ".join(shlex.quote(w) for w in words)


def add_commands(commands) -> None:
    from model.methods import METHODS, family_of, with_role

    bench = commands.add_parser(
        "bench",
        help="every registered method on one scene (LeCO, vanilla Switch-NeRF, the occupancy grid, "
        "proposal networks): report, plots",
    )
    bench.add_argument("--scene", help="scene folder (any supported format)")
    bench.add_argument(
        "--suite",
        help="a suite of scenes instead of one (bench/suites/: dev, held-out; or a .toml path), "
        "run from a frozen copy of HEAD; --methods, --seeds and --scenes narrow it",
    )
    bench.add_argument(
        "--scenes", help="with --suite: comma-separated scene names of the suite to run"
    )
    bench.add_argument(
        "--commit",
        help="with --suite: the commit to freeze and train (default HEAD), e.g. the one a "
        "committed records folder was made at",
    )
    bench.add_argument(
        "--records",
        help="with --suite: the folder of finished runs the tables are read from and new runs "
        "are added to (default OUT/records); commit it to finish the suite in a later checkout",
    )
    bench.add_argument("--profile", default="cpu", help="smoke | cpu | paper (default: cpu)")
    bench.add_argument("--out", required=True, help="output folder; finished runs in it are reused")
    bench.add_argument(
        "--budget-min",
        type=float,
        default=None,
        help="wall-clock training budget per method in minutes (LeCO's includes its occupancy "
        "phase); without it every method runs the profile's step counts",
    )
    bench.add_argument(
        "--methods",
        help=f"comma-separated, from: {', '.join(METHODS)}, or an earlier default (bench/"
        f"variants.py CONFIGURATIONS), either with settings of its own to train beside it "
        f"(leco+occupancy.min_steps=900) (default: the Switch-NeRF family, "
        f"{', '.join(family_of(with_role('ours')))}; with --suite, the suite's)",
    )
    bench.add_argument(
        "--ladder",
        action="store_true",
        help="also train the ablation ladder: LeCO from the paper's formulation to the profile's "
        "defaults, one change at a time (bench/variants.py RUNGS)",
    )
    bench.add_argument(
        "--sweep",
        action="store_true",
        help="also train each method at a leaner and a richer sampling budget (and LeCO with "
        "transmittance culling): PSNR against samples per ray and rays/s in the report",
    )
    bench.add_argument(
        "--ablation",
        action="store_true",
        help="also train the ablations: homogeneous MoE and HMoE without the density loss",
    )
    bench.add_argument(
        "--seeds", help="comma-separated seeds, e.g. 0,1,2 (default: 0; with --suite, the suite's)"
    )
    bench.add_argument(
        "--eval-every-s",
        type=float,
        default=None,
        help="validation every this many training seconds (default: budget/15, or 30 s)",
    )
    bench.add_argument(
        "--eval-views", type=int, default=4, help="validation views scored during training"
    )
    bench.add_argument(
        "--backend",
        default="local",
        choices=["local", "ray"],
        help="local (default): one process per method; ray: Ray Train workers",
    )
    bench.add_argument("--workers", type=int, default=1, help="data-parallel workers (ray backend)")
    bench.add_argument("--gpu", action="store_true", help="train on GPUs")
    bench.add_argument(
        "--downscale",
        type=int,
        default=None,
        help="integer factor for images and intrinsics, in training and evaluation alike (default: "
        "the scene's own scale; the paper uses 4 on Mega-NeRF scenes)",
    )
    bench.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="profile override for every method (`leco settings` lists them)",
    )
    bench.set_defaults(func=bench_command)

"""Running a job: the run directory, Ray Train (V2) `TorchTrainer` over N workers (or one local
process), a progress callback fed from the metrics file, final evaluation and RUN_DIR/summary.json.

With RAY_ADDRESS set the same code runs on that cluster (RUN_DIR must then be on storage every node
mounts at the same path); otherwise a local Ray is started with as many CPUs as there are workers.
"""

from __future__ import annotations

import json
import os
import platform
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from workers.config import TrainConfig
from workers.store import RunError, RunGaveUp, RunInterrupted, RunStore
from workers.train.evaluate import evaluate_run
from workers.train.loop import NonFiniteRun, RankRun, RunStopped, StoreFailed, write_pid
from workers.train.session import LocalSession, RaySession
from workers.train.sinks import read_metrics

SUMMARY = "summary.json"
HEALTH_CHECK_ENV, HEALTH_CHECK_S = "RAY_TRAIN_HEALTH_CHECK_INTERVAL_S", "0.5"
__all__ = ["SUMMARY", "RunError", "RunGaveUp", "RunInterrupted", "run_training"]


def end_cleanly(run: RankRun, run_dir: Path) -> None:
    """Runs the loop; failures that a retry would only repeat, and stop requests, end it with a
    record (rank 0) instead of an exception Ray Train would answer with a restart."""
    try:
        run.train()
    except (NonFiniteRun, StoreFailed) as error:
        if run.session.rank == 0:
            write_json(
                run_dir / "failure.json",
                {"reason": str(error), "retryable": bool(getattr(error, "retryable", False))},
            )
    except RunStopped as error:
        if run.session.rank == 0:
            write_json(run_dir / "stopped.json", {"reason": str(error)})


def write_json(path: Path, data: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1, sort_keys=True))
    tmp.replace(path)


def prepare_run_dir(
    cfg: TrainConfig, scene_dir: Path, run_dir: Path, resume_from: Path | None = None
) -> TrainConfig:
    """Creates RUN_DIR/run.json, or checks that an existing one is this same run (then it resumes).
    Returns the job pinned to the profile the run trains with: the one it started with when it
    resumes (run.json, or the checkpoint it resumes from), so a changed profile default never
    switches a run's settings midway."""
    run_dir.mkdir(parents=True, exist_ok=True)
    record = {"config": cfg.model_dump(mode="json"), "scene": str(Path(scene_dir).resolve())}
    existing = run_dir / "run.json"
    profile = None
    if existing.exists():
        if (run_dir / SUMMARY).exists():
            raise RunError(
                f"{run_dir} holds a finished run (summary.json exists): choose a new --out"
            )
        old = json.loads(existing.read_text())
        if {k: old.get(k) for k in record} != record:
            raise RunError(
                f"{run_dir} holds a different run (its run.json has another config or scene); "
                "resume it with the same arguments or choose a new --out"
            )
        profile = old.get("resolved_profile")
    if profile is None and resume_from is not None:  # a service attempt starting from a checkpoint
        profile = saved_profile(resume_from / "state.pt")
    try:
        pinned = cfg.pinned(profile if profile is not None else cfg.resolved_profile())
    except ValueError as error:
        raise RunError(f"{run_dir}: cannot resume: {error}") from None
    record["resolved_profile"] = pinned.resolved_profile().model_dump(mode="json")
    write_json(existing, record)
    return pinned


def saved_profile(state: Path) -> dict | None:
    """The resolved profile a checkpoint or final/models.pt was trained with (None from versions
    that did not save it). Memory-mapped: the tensors are not read."""
    if not state.is_file():
        return None
    saved = torch.load(state, map_location="cpu", weights_only=False, mmap=True)
    return saved.get("resolved_profile")


def device_for(use_gpu: bool) -> torch.device:
    if use_gpu:
        import ray.train.torch

        return ray.train.torch.get_device()
    return torch.device("cpu")


def train_loop_per_worker(config: dict) -> None:
    """Ray Train entry point: every worker runs this."""
    cfg = TrainConfig.model_validate(config["train"]).pinned(config["profile"])
    session = RaySession(Path(config["resume_from"]) if config.get("resume_from") else None)
    run_dir = Path(config["run_dir"])
    write_pid(run_dir, session.rank)
    torch.set_num_threads(max(1, int(config.get("threads", 1))))
    run = RankRun(
        cfg, Path(config["scene"]), run_dir, session, device_for(cfg.use_gpu), config.get("store")
    )
    end_cleanly(run, run_dir)


def ensure_ray(num_cpus: int, num_gpus: int | None = None) -> None:
    """A Ray for this process: the cluster RAY_ADDRESS names, else a local one of `num_cpus` CPUs
    and `num_gpus` GPUs (None: the GPUs Ray finds)."""
    import ray

    if ray.is_initialized():
        return
    # A local Ray on this machine needs no token; a cluster brings its own setting (REFERENCE.md
    # section 6).
    if os.environ.get("RAY_ADDRESS"):
        ray.init(address=os.environ["RAY_ADDRESS"])
    else:
        os.environ.setdefault("RAY_AUTH_MODE", "disabled")
        ray.init(num_cpus=num_cpus, num_gpus=num_gpus, include_dashboard=False, log_to_driver=False)


def fit_with_ray(
    cfg: TrainConfig,
    scene_dir: Path,
    run_dir: Path,
    store: RunStore | None,
    resume_from: Path | None,
) -> None:
    import ray.train
    from ray.train.torch import TorchTrainer

    # Ray Train's controller notices that the workers have finished (or died) at its next health
    # check: at its default 2 s a 20-step job ended 4.7 s after its last step, at 0.5 s 1.5-2.1 s
    # (tiny city, two CPU workers). Passed on to the controller; a setting of the caller's own wins.
    os.environ.setdefault(HEALTH_CHECK_ENV, HEALTH_CHECK_S)
    threads = (
        max(1, (os.cpu_count() or 2) // cfg.workers) if not os.environ.get("RAY_ADDRESS") else 1
    )
    trainer = TorchTrainer(
        train_loop_per_worker,
        train_loop_config={
            "train": cfg.model_dump(mode="json"),
            "profile": cfg.resolved_profile().model_dump(mode="json"),
            "scene": str(scene_dir),
            "run_dir": str(run_dir),
            "threads": threads,
            "store": store,
            "resume_from": str(resume_from) if resume_from else None,
        },
        scaling_config=ray.train.ScalingConfig(
            num_workers=cfg.workers,
            use_gpu=cfg.use_gpu,
            resources_per_worker=None if cfg.use_gpu else {"CPU": 1},
        ),
        # Same storage_path and name on a re-run: Ray Train hands the loop the last checkpoint
        # (resume).
        run_config=ray.train.RunConfig(
            name="train",
            storage_path=str((run_dir / "ray").resolve()),
            failure_config=ray.train.FailureConfig(max_failures=cfg.max_failures),
            checkpoint_config=ray.train.CheckpointConfig(num_to_keep=2),
        ),
    )
    trainer.fit()


def fit_locally(
    cfg: TrainConfig,
    scene_dir: Path,
    run_dir: Path,
    store: RunStore | None,
    resume_from: Path | None,
) -> None:
    if cfg.workers != 1:
        raise RunError(
            f"the local backend runs one worker, not {cfg.workers}: use --backend ray for more"
        )
    if cfg.use_gpu and not torch.cuda.is_available():
        raise RunError("--gpu asked for, but this machine has no CUDA device")
    device = torch.device("cuda") if cfg.use_gpu else torch.device("cpu")
    end_cleanly(
        RankRun(
            cfg,
            scene_dir,
            run_dir,
            LocalSession(run_dir / "checkpoints", resume_from),
            device,
            store,
        ),
        run_dir,
    )


# Per-step figures of the main phase that the summary averages (the methods' own are in their
# `stats`).
SAMPLING_KEYS = (
    "occupancy_ratio",
    "samples_per_hit_ray",
    "hit_ray_fraction",
    "samples_per_ray",
    "o_kept_ratio",
    "fallback_fraction",
    "proposal_samples_per_ray",
)


def summarise(cfg: TrainConfig, run_dir: Path, evaluation: dict, attempt_s: float) -> dict:
    metrics = read_metrics(run_dir / "metrics.jsonl")
    progress = json.loads((run_dir / "final" / "progress.json").read_text())
    elapsed = progress["elapsed"]
    main = [m for m in metrics if m.get("phase") == "main"]
    first_phase = [m for m in metrics if m.get("phase") not in (None, "main")]
    mean = lambda rows, key: (
        float(np.mean([r[key] for r in rows if r.get(key) is not None])) if rows else None
    )
    occupancy = dict(evaluation.get("occupancy") or {})
    occupancy.update(cfg.method_for_run().summary_occupancy(run_dir / "final", main, first_phase))
    device = (
        torch.cuda.get_device_name(0)
        if cfg.use_gpu and torch.cuda.is_available()
        else f"CPU ({platform.processor() or platform.machine()}, {os.cpu_count()} cores)"
    )
    return {
        "method": cfg.method,
        "profile": cfg.profile,
        "config": cfg.model_dump(mode="json"),
        "resolved_profile": cfg.resolved_profile().model_dump(mode="json"),
        # phases/total: training compute (what the budget and rays/s count); this_attempt: the
        # driver's clock for this invocation, with start-up, checkpoints and evaluation.
        "wall_time_s": {
            "phases": elapsed,
            "total": sum(elapsed.values()),
            "this_attempt": attempt_s,
        },
        "steps": {"total": progress["step"], "phases": progress["steps"]},
        # all the main phase's rays over all its training time: a mean of the logged windows'
        # rates would weigh a window of grid updates as lightly as a fast one
        "rays_per_s": (
            cfg.global_batch * progress["steps"].get("main", 0) / elapsed["main"]
            if elapsed.get("main")
            else None
        ),
        "samples_per_ray": mean(main, "samples_per_ray"),
        # What reached the main network while training, counted alike for every method
        # (model/render/accounting.py)
        "sampling": {
            k: mean(main, k) for k in SAMPLING_KEYS if any(r.get(k) is not None for r in main)
        },
        "occupancy": occupancy or None,
        "val": evaluation["val"],
        "rays": evaluation.get("rays"),
        "peak_memory_mb": max((m.get("peak_memory_mb") or 0.0 for m in metrics), default=None),
        # What autograd keeps for one step of the main network (workers/memory.py): the memory the
        # samplers set.
        "activation_memory_mb": max(
            (m.get("activation_memory_mb") or 0.0 for m in main), default=None
        ),
        "device": device,
        "world_size": cfg.workers,
        "point_cloud": evaluation["point_cloud"],
    }


def run_training(
    cfg: TrainConfig,
    scene_dir: str | Path,
    run_dir: str | Path,
    backend: str = "ray",
    on_progress: Callable[[dict], None] | None = None,
    poll_s: float = 1.0,
    store: RunStore | None = None,
    resume_from: Path | None = None,
) -> dict:
    """Train (or resume) a run to the end, evaluate it, write summary.json and return it. With a
    `store`, rank 0 also reports metrics, checkpoints and renders to it and stops when it asks
    (RunInterrupted). `resume_from`: a folder with a checkpoint's state.pt to start from while the
    run has none of its own."""
    started = time.perf_counter()
    # Ray's workers run elsewhere
    scene_dir, run_dir = Path(scene_dir).resolve(), Path(run_dir).resolve()
    from model.scenes import load_scene

    # a broken scene fails here, before any worker starts
    load_scene(scene_dir, downscale=cfg.downscale)
    cfg = prepare_run_dir(cfg, scene_dir, run_dir, resume_from)
    (run_dir / "failure.json").unlink(missing_ok=True)
    (run_dir / "stopped.json").unlink(missing_ok=True)
    fit = fit_with_ray if backend == "ray" else fit_locally
    if backend == "ray":
        ensure_ray(max(2, cfg.workers))  # in the main thread: Ray installs signal handlers there
    # Training runs in this thread; a side thread reports progress. PyTorch's CPU kernels run
    # 1.4-1.7x slower in a second thread once this one has used its OpenMP pool (load_scene above
    # does): measured on the `cpu` profile, a LeCO main step 28 -> 47 ms, a vanilla one 88 -> 126 ms
    # (docs/EXPERIMENTS.md, 2026-11-24).
    done = threading.Event()
    watcher = None
    if on_progress is not None:
        watcher = threading.Thread(
            target=_watch, args=(run_dir, on_progress, poll_s, done), daemon=True
        )
        watcher.start()
    try:
        fit(cfg, scene_dir, run_dir, store, resume_from)
    except Exception as error:
        raise RunError(f"training failed: {error}") from error
    finally:
        done.set()
        if watcher is not None:
            watcher.join()
    if on_progress is not None:
        _report_last(run_dir, on_progress)
    if (run_dir / "failure.json").exists():
        failure = json.loads((run_dir / "failure.json").read_text())
        raise (RunGaveUp if failure.get("retryable") else RunError)(failure["reason"])
    if (run_dir / "stopped.json").exists():
        raise RunInterrupted(json.loads((run_dir / "stopped.json").read_text())["reason"])
    # On a GPU when this process has one (a Ray driver may not): a paper-size model's
    # full-resolution views take minutes on a CPU.
    evaluation = evaluate_run(
        run_dir, "cuda" if cfg.use_gpu and torch.cuda.is_available() else "cpu"
    )
    summary = summarise(cfg, run_dir, evaluation, time.perf_counter() - started)
    write_json(run_dir / SUMMARY, summary)
    return summary


def _watch(
    run_dir: Path, on_progress: Callable[[dict], None], poll_s: float, done: threading.Event
) -> None:
    while not done.wait(poll_s):
        _report_last(run_dir, on_progress)


def _report_last(run_dir: Path, on_progress: Callable[[dict], None]) -> None:
    rows = read_metrics(run_dir / "metrics.jsonl")
    if rows:
        on_progress(rows[-1])

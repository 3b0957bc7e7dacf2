"""The pipeline in a process of its own: COLMAP's C++ may use every core and much memory, and a
crash or an allocation failure there must end the run, not its caller (the CLI, or the service's
attempt). The child sends events on a queue; the parent passes them on, stops the child on a cancel
or past the time limit, and turns how the child ended into an error that says why."""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import queue
import signal
import sys
import time
from pathlib import Path
from typing import Any, Callable

from model.errors import Failed, InvalidInput, LecoError
from workers.poses.pipeline import Report, check_output, find_poses
from workers.poses.settings import PosesConfig

POLL_S = 0.2
PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


class PosesCancelled(Failed):
    """The run was stopped on request; the work folder keeps what was finished."""


def _die_with(parent_pid: int) -> None:
    """The pycolmap process ends with the process that started it, even one killed outright (Linux's
    parent-death signal): an orphan would go on writing the work folder a later run resumes from."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it stops this one
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent_pid:  # it died before the line above took effect
        sys.exit(f"the process that started this one (pid {parent_pid}) is gone")


def _child(photos: str, out: str, config: dict, events: Any, parent_pid: int) -> None:
    """The pycolmap process: limits first, then the pipeline; every outcome is a message."""
    _die_with(parent_pid)
    settings = PosesConfig.model_validate(config)
    if settings.memory_limit_mb:
        import resource

        limit = settings.memory_limit_mb << 20
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    try:
        summary = find_poses(Path(photos), Path(out), settings, events.put)
    except LecoError as exc:
        events.put({"event": "error", "kind": exc.kind, "message": str(exc)})
    except MemoryError:
        events.put({"event": "error", "kind": "failed", "message": _memory_message(settings)})
    except Exception as exc:  # COLMAP's own errors reach Python as RuntimeError and others
        text = f"{type(exc).__name__}: {exc}".strip()
        if settings.memory_limit_mb:  # an allocation refused under the limit takes many forms
            text += f" (under memory_limit_mb={settings.memory_limit_mb}: the limit may be why)"
        events.put({"event": "error", "kind": "failed", "message": text})
    else:
        events.put({"event": "done", "summary": summary})


def _memory_message(config: PosesConfig) -> str:
    return (
        f"pycolmap ran out of memory under memory_limit_mb={config.memory_limit_mb} (lower "
        "max_image_size, or raise the limit)"
    )


def _death(code: int | None, stage: str, config: PosesConfig) -> str:
    if code is not None and code < 0:
        name = signal.Signals(-code).name if -code in signal.Signals._value2member_map_ else -code
        why = f"was killed by {name}"
    else:
        why = f"exited with status {code}"
    hint = (
        f"; with memory_limit_mb={config.memory_limit_mb}, most likely that limit"
        if config.memory_limit_mb
        else ""
    )
    return f"the pycolmap process {why} during {stage or 'start-up'}{hint}"


def run_poses(
    photos: Path,
    out: Path,
    config: PosesConfig,
    report: Report,
    cancelled: Callable[[], bool] = lambda: False,
) -> dict:
    """find_poses in a child process: the same summary, or the same errors (InvalidInput for what
    the photos or settings got wrong, Failed for the rest); PosesCancelled on a cancel."""
    check_output(Path(out))
    context = multiprocessing.get_context("spawn")  # no fork of a caller holding threads
    events = context.Queue()
    child = context.Process(
        target=_child,
        args=(str(photos), str(out), config.model_dump(), events, os.getpid()),
        name="leco-poses",
        daemon=True,
    )
    started = time.monotonic()
    child.start()
    stage = ""
    try:
        while True:
            alive = child.is_alive()  # before the read: a child's last events are read first
            try:
                event = events.get(timeout=POLL_S if alive else 1.0)
            except queue.Empty:
                event = None
            if event is not None:
                kind = event["event"]
                if kind == "done":
                    return event["summary"]
                if kind == "error":
                    error = InvalidInput if event["kind"] == "invalid" else Failed
                    raise error(event["message"])
                if kind == "stage":
                    stage = event["stage"]
                report(event)
            elif not alive:
                child.join()
                raise Failed(_death(child.exitcode, stage, config))
            if cancelled():
                raise PosesCancelled(f"cancelled during {stage or 'start-up'}")
            limit = config.time_limit_s
            if limit is not None and time.monotonic() - started > limit:
                raise Failed(
                    f"stopped after time_limit_s={limit:g} s during {stage or 'start-up'}: the "
                    "finished stages "
                    "are kept, and the same command goes on from them"
                )
    finally:
        if child.is_alive():  # SIGKILL: its state is saved a stage or a chunk at a time, and
            # COLMAP's failure-signal handler would print a stack trace for a SIGTERM
            child.kill()
            child.join()
        events.close()

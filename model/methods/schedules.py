"""Schedules over a phase's progress in [0, 1]: the fraction of its steps or of its wall-clock
allotment spent, whichever is larger, so a run under a time budget reaches the final value when its
time runs out."""

from __future__ import annotations


def log_linear(start: float, final: float | None, progress: float) -> float:
    """start * (final / start) ** progress (exponential decay); constant when final is None."""
    if final is None or start == final:
        return start
    if start <= 0 or final <= 0:  # a weight decaying to or from zero: linear instead
        return start + (final - start) * min(max(progress, 0.0), 1.0)
    return start * (final / start) ** min(max(progress, 0.0), 1.0)


def phase_progress(
    step: int, total_steps: int, elapsed_s: float, allotted_s: float | None, min_steps: int = 0
) -> float:
    """How far a phase is: steps done over its step count, or training seconds over its time
    allotment. A phase that must take `min_steps` before its allotment stops it is no further
    than those steps say, so its schedule ends with them when they outlast the allotment."""
    progress = step / max(total_steps, 1)
    if allotted_s is not None and allotted_s > 0:
        timed = elapsed_s / allotted_s
        if min_steps:
            timed = min(timed, step / min_steps)
        progress = max(progress, timed)
    return min(progress, 1.0)

"""Where per-step metrics go: a small sink interface. The CLI writes JSON lines; the service writes
the database. Writes are idempotent per (run, metric, step): after a restart from a checkpoint the
replayed steps overwrite what the lost attempt wrote, never duplicate it."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Protocol


class MetricSink(Protocol):
    def resume(self, step: int) -> None:
        """Forget everything after `step` (the checkpoint a restarted attempt continues from)."""

    def write(self, step: int, metrics: dict[str, float | str | None]) -> None: ...


def clean(value: float | str | None) -> float | str | None:
    """JSON has no NaN or Inf: they are written as null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


class JsonlSink:
    """One line per step: {"step": s, ...metrics}; `read` returns the last write of each step."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    def resume(self, step: int) -> None:
        kept = [r for r in read_metrics(self.path) if r["step"] <= step]
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text("".join(json.dumps(r, sort_keys=True) + "\n" for r in kept))
        os.replace(tmp, self.path)

    def write(self, step: int, metrics: dict) -> None:
        record = {"step": step, **{k: clean(v) for k, v in metrics.items()}}
        with self.path.open("a") as f:
            f.write(json.dumps(record, sort_keys=True) + "\n")
            f.flush()


def read_metrics(path: str | Path) -> list[dict]:
    """Records in step order, the last write of each step winning (a torn last line is ignored)."""
    path = Path(path)
    if not path.exists():
        return []
    by_step: dict[int, dict] = {}
    for line in path.read_text().splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue
        by_step[int(record["step"])] = record
    return [by_step[s] for s in sorted(by_step)]

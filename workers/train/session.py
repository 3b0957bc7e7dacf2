"""What the training loop needs from its runner: rank, world size, the checkpoint to resume from,
and a way to register a checkpoint. `RaySession` is Ray Train (V2); `LocalSession` runs one process
without Ray (quick checks and debugging) with the same checkpoint semantics."""

from __future__ import annotations

import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Protocol


class Session(Protocol):
    rank: int
    world_size: int

    @contextmanager
    def resume_dir(self) -> Iterator[Path | None]: ...

    def report(self, metrics: dict, checkpoint_dir: Path | None) -> None: ...


class RaySession:
    """`seed`: a checkpoint folder to start from when Ray Train has none of its own yet (a later
    service attempt resuming in a fresh folder; Ray Train V2 has no resume_from_checkpoint)."""

    def __init__(self, seed: Path | None = None):
        import ray.train

        self._train = ray.train
        self.seed = seed
        context = ray.train.get_context()
        self.rank, self.world_size = context.get_world_rank(), context.get_world_size()

    @contextmanager
    def resume_dir(self) -> Iterator[Path | None]:
        checkpoint = self._train.get_checkpoint()
        if checkpoint is None:
            yield self.seed
            return
        with checkpoint.as_directory() as path:
            yield Path(path)

    def report(self, metrics: dict, checkpoint_dir: Path | None) -> None:
        checkpoint = (
            self._train.Checkpoint.from_directory(str(checkpoint_dir)) if checkpoint_dir else None
        )
        self._train.report(metrics, checkpoint=checkpoint)


class LocalSession:
    """Keeps the latest checkpoint in `root/latest` (replaced atomically); `seed` as for
    RaySession."""

    rank, world_size = 0, 1

    def __init__(self, root: Path, seed: Path | None = None):
        self.root, self.seed = Path(root), seed

    @contextmanager
    def resume_dir(self) -> Iterator[Path | None]:
        latest = self.root / "latest"
        yield latest if latest.is_dir() else self.seed

    def report(self, metrics: dict, checkpoint_dir: Path | None) -> None:
        if checkpoint_dir is None:
            return
        self.root.mkdir(parents=True, exist_ok=True)
        staging = self.root / "incoming"
        shutil.rmtree(staging, ignore_errors=True)
        shutil.copytree(checkpoint_dir, staging)
        old = self.root / "previous"
        shutil.rmtree(old, ignore_errors=True)
        if (self.root / "latest").exists():
            (self.root / "latest").rename(old)
        staging.rename(self.root / "latest")
        shutil.rmtree(old, ignore_errors=True)

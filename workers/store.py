"""The small interface through which a run reports to whoever launched it. The service implements it
on its database and artifact store (service/runstore.py); a `leco train` run has none and keeps
everything in its run directory. Only rank 0 holds one."""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

from model.errors import Failed


class StoreWriteError(Failed):
    """A write the store cannot make, and retrying would not help (disk full, an unwritable artifact
    root, the database away for longer than its retries): the run stops on every rank at the next
    step boundary, keeping its last checkpoint, and fails with this reason. `retryable` errors are
    not the run's fault (the store was away, or another attempt now holds the job): the launcher
    hands the job on instead of failing it."""

    retryable = False


class StopRequested(Failed):
    """A job's work stopped because its store asked it to (`stop_reason`): cancelled, or its lease
    lost."""


class RunError(Failed):
    """A run that cannot start or did not finish, with the reason a user can act on."""


class RunInterrupted(RunError, StopRequested):
    """The run's store asked it to stop (cancelled, lease lost); it stopped after a checkpoint."""


class RunGaveUp(RunError):
    """The run stopped because its store went away past its retries or another attempt holds the
    job: not a failure of the job, which a later attempt resumes from its last stored checkpoint."""


def check_stop(store: "RunStore | None") -> None:
    """Raises StopRequested when the store asks the work to stop; between frames or views of a
    render job."""
    reason = store.stop_reason() if store is not None else None
    if reason is not None:
        raise StopRequested(reason)


class RunStore(Protocol):
    def resume(self, step: int) -> None:
        """A restarted attempt continues from the checkpoint at `step`: forget metrics after it."""

    def write(self, step: int, metrics: dict) -> None:
        """One metrics record (numbers, plus 'phase'); idempotent per (phase, name, step). Every
        method raises StoreWriteError for a write that failed for good."""

    def artifact(
        self, kind: str, path: Path, *, name: str, phase: str | None, step: int | None
    ) -> None:
        """Stores a file the run wrote (checkpoint, render, ...) under `name`; the same name again
        replaces it."""

    def phase_started(self, phase: str) -> None: ...

    def stop_reason(self) -> str | None:
        """Why the run should stop at this step boundary (cancelled, lease lost), or None to go on.
        Called every step: implementations keep it cheap."""

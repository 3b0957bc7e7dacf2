"""Rank 0's reports to whoever launched the run (workers/store.py's RunStore: the service's
database, or none under `leco train`). A write that failed for good is remembered, not raised:
raising on one rank would leave the others waiting in a collective, so the loop ends the run on
every rank at the next step boundary."""

from __future__ import annotations

from workers.store import RunStore, StoreWriteError


class StoreReporter:
    def __init__(self, store: RunStore | None):
        """`store`: rank 0's; the other ranks report nothing (None)."""
        self.store = store
        # the first StoreWriteError, and whether another attempt could do better (its retryable)
        self.error: str | None = None
        self.retryable = False

    def __call__(self, method: str, *args: object, **kwargs: object) -> None:
        """Calls the store's `method` (write, artifact, phase_started, resume) unless a write has
        already failed."""
        if self.store is None or self.error is not None:
            return
        try:
            getattr(self.store, method)(*args, **kwargs)
        except StoreWriteError as error:
            self.error, self.retryable = str(error), error.retryable

    def stop_reason(self) -> str | None:
        """Why the launcher asks the run to stop (a cancel, a lost lease), if it does."""
        return self.store.stop_reason() if self.store is not None else None

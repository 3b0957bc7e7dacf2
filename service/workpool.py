"""A small bounded pool for heavy work the API process must do itself (extracting and decoding an upload,
generating a synthetic scene): at most `workers` run at once and `queue` more wait; beyond that a request is
refused at once with `Busy` (the API answers 429 with Retry-After) instead of piling up threads, disk and
memory."""

from __future__ import annotations

import threading
from contextlib import contextmanager
from typing import Iterator

RETRY_AFTER_S = 10


class Busy(RuntimeError):
    pass


class WorkPool:
    def __init__(self, workers: int, queue: int, what: str):
        self._running = threading.BoundedSemaphore(workers)
        self._admitted = threading.BoundedSemaphore(workers + queue)
        self.workers, self.queue, self.what = workers, queue, what

    def admit(self, wait: bool = False) -> None:
        """Take a place (running or waiting), or raise Busy (wait: block for one instead); `release` gives it
        back."""
        if not self._admitted.acquire(blocking=wait):
            raise Busy(f"{self.workers} {self.what} are running and {self.queue} waiting, the most this server "
                       f"takes at once; retry in {RETRY_AFTER_S} s")

    def release(self) -> None:
        self._admitted.release()

    @contextmanager
    def admitted(self) -> Iterator[None]:
        self.admit()
        try:
            yield
        finally:
            self.release()

    @contextmanager
    def running(self) -> Iterator[None]:
        """Wait for a free worker (the caller already holds an admitted place)."""
        with self._running:
            yield

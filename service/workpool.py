"""A small bounded pool for heavy work the API must start itself (extracting and decoding an upload,
generating a synthetic scene): at most `workers` run at once and `queue` more wait; beyond that a
request is refused at once with `Busy` (the API answers 429 with Retry-After) instead of piling up
threads, disk and memory. The work itself runs in the pool's own processes (`call`), so decoding a
large upload never holds the API process's interpreter lock: requests keep being answered while it
runs."""

from __future__ import annotations

import multiprocessing
import os
import threading
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from typing import Any, Callable, Iterator

from model import errors

RETRY_AFTER_S = 10
NICE = 10  # the pool's processes' niceness, added to the API process's


class Busy(errors.Busy):
    """Every worker process of the pool is taken."""


class WorkerLost(errors.Unavailable):
    """The process running the work stopped (killed, most likely out of memory) before it
    answered."""


class WorkPool:
    def __init__(self, workers: int, queue: int, what: str):
        self._running = threading.BoundedSemaphore(workers)
        self._places = threading.Condition()
        self._taken = 0  # running and waiting
        self.workers, self.queue, self.what = workers, queue, what
        self._executor: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()

    def admit(self, wait: bool = False) -> None:
        """Take a place (running or waiting), or raise Busy (wait: block for one instead); `release`
        gives it back."""
        with self._places:
            while self.full:
                if not wait:
                    raise self.busy()
                self._places.wait()
            self._taken += 1

    def release(self) -> None:
        with self._places:
            if self._taken == 0:
                raise ValueError("WorkPool.release without an admitted place")
            self._taken -= 1
            self._places.notify()

    def busy(self) -> Busy:
        return Busy(
            f"{self.workers} {self.what} are running and {self.queue} waiting, the most this "
            f"server takes at once; retry in {RETRY_AFTER_S} s"
        )

    @property
    def full(self) -> bool:
        """No place left (a hint outside the lock: `admit` decides)."""
        return self._taken >= self.workers + self.queue

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

    def call(self, fn: Callable[..., Any], *args: Any) -> Any:
        """fn(*args) in one of the pool's processes; the caller holds a running place. fn and its
        arguments cross a process boundary: a module-level function, plain data."""
        with self._lock:
            # spawned, not forked: the API process has threads and open sockets
            if self._executor is None:
                # Niced: decoding is background work, and the API answering its pollers must win the
                # cores.
                self._executor = ProcessPoolExecutor(
                    self.workers,
                    mp_context=multiprocessing.get_context("spawn"),
                    initializer=os.nice,
                    initargs=(NICE,),
                )
            executor = self._executor
        try:
            return executor.submit(fn, *args).result()
        except BrokenProcessPool:
            with self._lock:  # the next call starts fresh processes
                if self._executor is executor:
                    self._executor = None
            executor.shutdown(wait=False, cancel_futures=True)
            raise WorkerLost(
                f"the process doing one of the {self.what} stopped before it finished (out of "
                "memory?); nothing was stored"
            ) from None

    def close(self) -> None:
        with self._lock:
            executor, self._executor = self._executor, None
        if executor is not None:
            executor.shutdown(wait=True, cancel_futures=True)

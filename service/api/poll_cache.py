"""A short-lived cache of the answers every dashboard polls: a job's view, its metrics, and the job
list.

Two hundred open dashboards ask for the same job several hundred times a second; the answer changes
only when training writes (every few steps). So each API process computes a job's view at most once
per `ttl_s` (LECO_POLL_CACHE_S, 0.5 s by default) and serves the encoded bytes to every poller
meanwhile; concurrent misses for one key share one database read (single flight) instead of queueing
hundreds of identical queries.

Consistency, within one API process:
- nothing served is older than `ttl_s`;
- a metrics answer is served only while the job view it was computed under is still the current one.
  Training writes a step's metrics and the job's progress in one transaction, so once a poller has
  seen a job view (say `succeeded`), every metrics answer it gets afterwards includes the metrics
  that view implies;
- this process's own writes (submit, cancel, delete) drop the job's entries and every job list at
  once, and no read that was already in flight then is stored.
Memory is bounded: at most `max_entries` answers (least recently stored dropped first) and one epoch
number."""

from __future__ import annotations

import asyncio
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable

from starlette.concurrency import run_in_threadpool

# the job id under which job lists are kept (real ids start at 1): every job's change touches them
LISTS = 0


@dataclass(frozen=True)
class Entry:
    body: bytes
    made_at: float
    view: bytes | None  # for metrics: the job view current when this answer was computed


class PollCache:
    def __init__(
        self, ttl_s: float, max_entries: int = 4096, clock: Callable[[], float] = time.monotonic
    ):
        self.ttl_s, self.max_entries, self.clock = ttl_s, max_entries, clock
        # Keys are tuples whose second item is the job id (LISTS for job lists): forget() matches on
        # it.
        self.entries: OrderedDict[tuple, Entry] = OrderedDict()
        self.in_flight: dict[tuple, tuple[bytes | None, int, asyncio.Task[Entry]]] = {}
        # Bumped by every forget(): a read begun before any forget is not stored. One number for all
        # jobs, not one per job, so the cache's memory stays bounded however many jobs it has ever
        # seen; a write then also leaves other jobs' reads in flight unstored (they are still
        # served), which writes' rarity makes cheap.
        self.epoch = 0
        self.lock = threading.Lock()  # forget() runs in worker threads, the rest on the event loop
        self.hits = self.misses = 0

    @property
    def enabled(self) -> bool:
        return self.ttl_s > 0

    async def job_view(self, job_id: int, compute: Callable[[], bytes]) -> bytes:
        if not self.enabled:
            return await run_in_threadpool(compute)
        return (await self._get(("job", job_id), compute, view=None)).body

    async def metrics(
        self,
        job_id: int,
        key: tuple,
        compute_view: Callable[[], bytes],
        compute: Callable[[], bytes],
    ) -> bytes:
        """A metrics answer tied to the job view current now (itself normally served from the
        cache)."""
        if not self.enabled:
            return await run_in_threadpool(compute)
        view = await self.job_view(job_id, compute_view)
        return (await self._get(("metrics", job_id, key), compute, view=view)).body

    async def job_list(self, key: tuple, compute: Callable[[], bytes]) -> bytes:
        if not self.enabled:
            return await run_in_threadpool(compute)
        return (await self._get(("jobs", LISTS, key), compute, view=None)).body

    def forget(self, job_id: int) -> None:
        """Drops the job's entries and every job list; safe to call from a worker thread (a request
        handler in the threadpool)."""
        with self.lock:
            self.epoch += 1
            for key in [k for k in self.entries if k[1] in (job_id, LISTS)]:
                del self.entries[key]

    async def _get(self, key: tuple, compute: Callable[[], bytes], view: bytes | None) -> Entry:
        entry = self.entries.get(key)
        if entry is not None and self.clock() - entry.made_at < self.ttl_s and entry.view == view:
            self.hits += 1
            return entry
        epoch = self.epoch
        pending = self.in_flight.get(key)
        # the same read is under way: share it
        if pending is not None and pending[:2] == (view, epoch):
            self.hits += 1
            return await asyncio.shield(pending[2])
        self.misses += 1
        # A task of its own, so that a requester that goes away does not cancel the read the others
        # wait for.
        task = asyncio.ensure_future(self._load(key, epoch, compute, view))
        # retrieved even if nobody waits
        task.add_done_callback(lambda t: t.cancelled() or t.exception())
        self.in_flight[key] = (view, epoch, task)
        return await asyncio.shield(task)

    async def _load(
        self, key: tuple, epoch: int, compute: Callable[[], bytes], view: bytes | None
    ) -> Entry:
        made_at = self.clock()
        try:
            entry = Entry(await run_in_threadpool(compute), made_at, view)
        finally:
            if self.in_flight.get(key, (None, None, None))[2] is asyncio.current_task():
                del self.in_flight[key]
        with self.lock:
            if self.epoch == epoch:
                self.entries[key] = entry
                self.entries.move_to_end(key)
                while len(self.entries) > self.max_entries:
                    self.entries.popitem(last=False)
        return entry

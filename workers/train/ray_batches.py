"""Where a run's ray batches are made: on its device when the split's pixels fit there, else on the
host a few batches ahead.

A batch drawn on the host and copied with `.to(device)` waits for the device seven times a step on
CUDA (one synchronous copy per tensor of the batch). So a GPU run keeps its split resident on the
device (model/scenes/rays.py RaySampler with `device`: colours, cameras and each epoch's order,
RESIDENT_BYTES_PER_PIXEL a pixel) while that is at most `pixels_on_device_max_mb`; a larger split
is drawn on the host by a thread (PrefetchedRays), pinned and copied on a side stream without a
wait. A CPU run draws on the host, which is its device. The batches are the same in every case,
and so is a resumed run's next batch."""

from __future__ import annotations

import queue
import threading
from typing import Any, Protocol

import torch
from torch import Tensor
from torch.profiler import record_function

from model.methods.stages import HOST_DRAW
from model.scenes.rays import RayBatch, RaySampler
from model.scenes.scene import Views
from model.sizes import RESIDENT_BYTES_PER_PIXEL, keeps_pixels_on_device

PREFETCH_DEPTH = 2  # batches drawn ahead: one being copied while the step uses the one before
_POLL_S = 0.1  # how often a full queue's producer looks whether it was told to stop


class RayBatches(Protocol):
    """What the loop and its checkpoints use of a sampler."""

    batch_size: int

    def next(self) -> RayBatch: ...
    def state_dict(self) -> dict: ...
    def load_state_dict(self, state: dict) -> None: ...


def resident_bytes(views: Views) -> int:
    """Device memory a resident sampler holds for these views."""
    return views.num_pixels * RESIDENT_BYTES_PER_PIXEL


def ray_batches(
    views: Views,
    aabb: Tensor,
    batch_size: int,
    seed: int,
    rank: int,
    world_size: int,
    device: torch.device,
    pixels_on_device_max_mb: float,
) -> RaySampler | PrefetchedRays:
    """The sampler of one rank: resident on a GPU when the split fits under the bound, prefetched
    from the host when it does not, the host's own on a CPU."""
    where = device if device.type != "cpu" else None
    fits = keeps_pixels_on_device(views.num_pixels, pixels_on_device_max_mb)
    if where is None or fits:
        return RaySampler(views, aabb, batch_size, seed, rank, world_size, device=where)
    host = RaySampler(views, aabb, batch_size, seed, rank, world_size)
    return PrefetchedRays(host, device)


class PrefetchedRays:
    """A host sampler drawn PREFETCH_DEPTH batches ahead on a thread. On CUDA each batch is pinned
    and copied on a side stream; the step's stream waits for that copy on the device, not the
    host. The state is the position after the last batch handed out (the thread runs ahead of it),
    so a checkpoint resumes with the very next batch the step would have had."""

    def __init__(self, sampler: RaySampler, device: torch.device, depth: int = PREFETCH_DEPTH):
        self.sampler, self.device, self.depth = sampler, device, depth
        self.batch_size = sampler.batch_size
        self._state = sampler.state_dict()
        self._stream = torch.cuda.Stream(device) if device.type == "cuda" else None
        self._queue: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def batches_per_epoch(self) -> int:
        return self.sampler.batches_per_epoch

    def next(self) -> RayBatch:
        if self._thread is None:
            self._start()
        kind, item = self._queue.get()
        if kind == "error":
            self._thread = None
            raise item
        batch, state, copied = item
        if copied is not None:  # the step's stream waits for the copy; the host does not
            stream = torch.cuda.current_stream(self.device)
            stream.wait_event(copied)
            for tensor in batch.__dict__.values():
                tensor.record_stream(stream)
        self._state = state
        return batch

    def state_dict(self) -> dict:
        return dict(self._state)

    def load_state_dict(self, state: dict) -> None:
        self.close()
        self.sampler.load_state_dict(state)
        self._state = self.sampler.state_dict()

    def close(self) -> None:
        """Stops the thread and drops the batches it drew ahead."""
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
        self._thread, self._queue = None, queue.Queue(maxsize=self.depth)
        self.sampler.load_state_dict(self._state)  # the batches drawn ahead are drawn again

    def _start(self) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._draw, args=(self._stop, self._queue), name="ray-batches", daemon=True
        )
        self._thread.start()

    def _draw(self, stop: threading.Event, out: queue.Queue) -> None:
        while not stop.is_set():
            try:
                with record_function(HOST_DRAW):
                    moved, copied = self._copy(self.sampler.next())
                item: tuple[str, Any] = ("batch", (moved, self.sampler.state_dict(), copied))
            except Exception as error:  # handed to the step, which raises it
                item = ("error", error)
            while not stop.is_set():
                try:
                    out.put(item, timeout=_POLL_S)
                    break
                except queue.Full:
                    continue
            if item[0] == "error":
                return

    def _copy(self, batch: RayBatch) -> tuple[RayBatch, torch.cuda.Event | None]:
        if self._stream is None:
            return batch.to(self.device), None
        with torch.cuda.stream(self._stream):
            moved = RayBatch(
                **{
                    k: v.pin_memory().to(self.device, non_blocking=True)
                    for k, v in batch.__dict__.items()
                }
            )
            copied = torch.cuda.Event()
            copied.record(self._stream)
        return moved, copied

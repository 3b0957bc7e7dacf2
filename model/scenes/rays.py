"""Rays in batches: pixel ids -> (origin, direction, near, far, image index, target colour), a
seeded shuffling sampler over every training pixel, and the sharding rule for data-parallel
ranks."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from model.scenes.bounds import ray_aabb
from model.scenes.cameras import pixel_rays
from model.scenes.permutation import FeistelPermutation
from model.scenes.pixel_cache import PixelCache
from model.scenes.scene import Views


@dataclass
class RayBatch:
    origins: Tensor  # (B, 3) world frame
    directions: Tensor  # (B, 3) unit
    near: Tensor  # (B,) start of the foreground segment (0 when the ray misses the box)
    far: Tensor  # (B,) end of the foreground segment, where the background begins
    image_index: Tensor  # (B,) int64 appearance-embedding index
    rgb: Tensor  # (B, 3) float32 in [0, 1]: target colour
    pixel: Tensor  # (B,) int64 global pixel id within its Views

    def __len__(self) -> int:
        return self.origins.shape[0]

    def to(self, device: torch.device | str) -> RayBatch:
        return RayBatch(**{k: v.to(device) for k, v in self.__dict__.items()})

    def subset(self, keep: Tensor) -> RayBatch:
        """The rays where `keep` (a bool mask or indices) selects, in order."""
        return RayBatch(**{k: v[keep] for k, v in self.__dict__.items()})


class PixelTable:
    """Flat pixel ids over all images of a Views: id = offset[image] + v * W + u. Colours come from
    a memory-mapped PixelCache (the one given, else the one attached to the views), else from one
    concatenated copy of the decoded images, made on the first colour read (small scenes, tests).

    `device`: where pixel ids are looked up and rays made (the cameras, offsets and appearance
    indices are copied there once). With `colours_on_device` the colours are copied there too
    (uint8, 3 bytes a pixel, image by image), so a batch is made without touching the host; else
    they are gathered on the host, which only a CPU device reads without a copy."""

    def __init__(
        self,
        views: Views,
        cache: PixelCache | None = None,
        device: torch.device | str | None = None,
        colours_on_device: bool = False,
    ):
        self.views = views
        self.device = torch.device(device if device is not None else "cpu")
        sizes = (views.cameras.width * views.cameras.height).long()
        self.offsets = torch.cat([torch.zeros(1, dtype=torch.long), sizes.cumsum(0)])
        cache = cache if cache is not None else views.cache
        if cache is not None and cache.offsets != self.offsets.tolist():
            raise ValueError(f"pixel cache {cache.folder} holds other image sizes than these views")
        self.cache = cache
        self.num_pixels = int(self.offsets[-1])  # read once: a batch's bounds check reads nothing
        self._colours: Tensor | None = None
        # decided once on the host: drawing a batch never reads a device tensor to choose a branch
        self.distorted = bool(views.cameras.distortion.any())
        self._offsets = self.offsets.to(self.device)
        self._cameras = views.cameras.to(self.device)
        self._appearance = views.appearance.to(self.device)
        if colours_on_device:
            self._colours = self._device_colours()

    def __len__(self) -> int:
        return self.num_pixels

    def _device_colours(self) -> Tensor:
        """Every pixel's colour on the device, copied image by image (the host holds one image at
        a time)."""
        colours = torch.empty(len(self), 3, dtype=torch.uint8, device=self.device)
        for i in range(len(self.views)):
            start, end = int(self.offsets[i]), int(self.offsets[i + 1])
            image = self.cache.image(i) if self.cache is not None else self.views.images[i]
            colours[start:end] = image.reshape(-1, 3).to(self.device)
        return colours

    def colours(self, pixel: Tensor) -> Tensor:
        """uint8 (B, 3) colours of flat pixel ids, on the device of the ids for a table whose
        colours are on its device, else on the host."""
        if self._colours is not None:
            return self._colours[pixel]
        if self.cache is not None:
            return self.cache.gather(pixel)
        self._colours = torch.cat([img.reshape(-1, 3) for img in self.views.images])
        return self._colours[pixel]

    def locate(self, pixel: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(image, u, v) of flat pixel ids (on the table's device)."""
        image = torch.searchsorted(self._offsets, pixel, right=True) - 1
        local = pixel - self._offsets[image]
        width = self._cameras.width[image]
        return image, local % width, local // width

    def geometry(
        self, pixel: Tensor, aabb: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """(image, origins, directions, near, far) of flat pixel ids: everything but the colours."""
        image, u, v = self.locate(pixel)
        origins, directions = pixel_rays(self._cameras, image, u, v, self.distorted)
        near, far = ray_aabb(origins, directions, aabb)
        return image, origins, directions, near, far

    def rays(self, pixel: Tensor, aabb: Tensor) -> RayBatch:
        image, origins, directions, near, far = self.geometry(pixel, aabb)
        rgb = self.colours(pixel).to(self.device).float() / 255.0
        return RayBatch(origins, directions, near, far, self._appearance[image], rgb, pixel)

    def image_pixels(self, image: int, columns: tuple[int, int] | None = None) -> Tensor:
        """Pixel ids of one image, row-major; with columns=(u0, u1) only the columns u0 <= u <
        u1."""
        ids = torch.arange(int(self.offsets[image]), int(self.offsets[image + 1]))
        if columns is None:
            return ids
        width = int(self.views.cameras.width[image])
        return ids.reshape(-1, width)[:, columns[0] : columns[1]].reshape(-1)

    def image_rays(
        self, image: int, aabb: Tensor, columns: tuple[int, int] | None = None
    ) -> RayBatch:
        """The rays of one image (or of its columns u0 <= u < u1), row-major, for validation
        renders."""
        return self.rays(self.image_pixels(image, columns), aabb)


def shard(batch: Tensor, rank: int, world_size: int) -> Tensor:
    """Rank `rank`'s disjoint, equal, contiguous share of a global batch."""
    if world_size < 1 or not 0 <= rank < world_size:
        raise ValueError(
            f"rank must be in [0, world_size), got rank={rank}, world_size={world_size}"
        )
    if len(batch) % world_size:
        raise ValueError(
            f"global batch of {len(batch)} rays does not split evenly over {world_size} ranks"
        )
    per_rank = len(batch) // world_size
    return batch[rank * per_rank : (rank + 1) * per_rank]


# Up to this many pixels (lego's 4.0M and fern's 3.8M at full size) a host sampler evaluates an
# epoch's order once and keeps it, so a batch is a slice of it rather than a Feistel evaluation
# (about 300 small ops and a data-dependent loop a step); the values are the same either way. 4
# bytes a pixel, 16 MiB at most: inside the memory estimate's 25% margin
# (model/memory_estimate.py), so it adds no term. A sampler on a GPU always keeps it, beside the
# colours it holds there (model/sizes.py RESIDENT_BYTES_PER_PIXEL).
KEPT_ORDER_MAX_PIXELS = 2**22
ORDER_CHUNK = 2**20  # pixels evaluated at once while an epoch's order is built


class RaySampler:
    """Seeded shuffling over all pixels: each epoch is one permutation keyed by (seed, epoch);
    global batches are consecutive slices of it (the incomplete tail is skipped) and every rank
    takes its shard of the same global batch. The permutation is evaluated per batch
    (model/scenes/permutation.py), so the sampler's memory is its batch, whatever the number of
    pixels; a split of at most KEPT_ORDER_MAX_PIXELS evaluates each epoch's order once and slices
    it. Its position is a state dict, so a resumed run continues with the very next batch.

    `device`: where batches are made. On a GPU the sampler is resident there: the colours, the
    cameras and each epoch's order live on the device, and a batch is drawn without a copy or a
    wait (model/sizes.py RESIDENT_BYTES_PER_PIXEL a pixel; workers/train/ray_batches.py decides
    when that fits and prefetches host batches when it does not; `resident=True` keeps a CPU
    sampler the same way). The batches are the same on every device and either way."""

    def __init__(
        self,
        views: Views,
        aabb: Tensor,
        batch_size: int,
        seed: int,
        rank: int = 0,
        world_size: int = 1,
        cache: PixelCache | None = None,
        device: torch.device | str | None = None,
        resident: bool | None = None,
    ):
        self.device = torch.device(device if device is not None else "cpu")
        resident = self.device.type != "cpu" if resident is None else resident
        self.table = PixelTable(views, cache, self.device, colours_on_device=resident)
        if batch_size % world_size:
            raise ValueError(
                f"batch_size {batch_size} must be a multiple of world_size {world_size}"
            )
        if batch_size > len(self.table):
            raise ValueError(
                f"batch_size {batch_size} exceeds the {len(self.table)} pixels of the split"
            )
        self.aabb, self.batch_size, self.seed = aabb.to(self.device), batch_size, seed
        self.rank, self.world_size = rank, world_size
        self.epoch, self.offset = 0, 0
        self.resident = resident
        self._perm: FeistelPermutation | None = None
        self._order: Tensor | None = None  # the epoch's whole order, when kept

    @property
    def batches_per_epoch(self) -> int:
        return len(self.table) // self.batch_size

    def _permutation(self) -> FeistelPermutation:
        if self._perm is None:
            self._perm = FeistelPermutation(len(self.table), self.seed * 1_000_003 + self.epoch)
        return self._perm

    def _kept_order(self) -> Tensor | None:
        """The epoch's whole order (int32, on the sampler's device), evaluated a chunk at a time on
        its first batch; None where it is not kept."""
        if not (self.resident or len(self.table) <= KEPT_ORDER_MAX_PIXELS):
            return None
        if self._order is None:
            n, perm = len(self.table), self._permutation()
            order = torch.empty(n, dtype=torch.int32, device=self.device)
            for start in range(0, n, ORDER_CHUNK):
                end = min(start + ORDER_CHUNK, n)
                order[start:end] = perm(torch.arange(start, end, device=self.device))
            self._order = order
        return self._order

    def _new_epoch(self, epoch: int, offset: int) -> None:
        self.epoch, self.offset, self._perm, self._order = epoch, offset, None, None

    def next_global(self) -> Tensor:
        """The next global batch of pixel ids (the same on every rank), on the sampler's device."""
        if self.offset + self.batch_size > len(self.table):
            self._new_epoch(self.epoch + 1, 0)
        end = self.offset + self.batch_size
        order = self._kept_order()
        if order is not None:
            batch = order[self.offset : end].long()
        else:
            batch = self._permutation()(torch.arange(self.offset, end))
        self.offset = end
        return batch

    def next(self) -> RayBatch:
        """The next batch of this rank's rays, on the sampler's device."""
        return self.table.rays(shard(self.next_global(), self.rank, self.world_size), self.aabb)

    def state_dict(self) -> dict:
        return {
            "seed": self.seed,
            "epoch": self.epoch,
            "offset": self.offset,
            "batch_size": self.batch_size,
        }

    def load_state_dict(self, state: dict) -> None:
        if state["seed"] != self.seed or state["batch_size"] != self.batch_size:
            raise ValueError(
                f"sampler state is for seed={state['seed']}, batch_size={state['batch_size']}; "
                f"this sampler has seed={self.seed}, batch_size={self.batch_size}"
            )
        self._new_epoch(int(state["epoch"]), int(state["offset"]))

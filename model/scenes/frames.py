"""A split's images (or depth maps) as a sequence that decodes an item when it is indexed, so that
loading a scene of thousands of photos holds their sizes and cameras, not their pixels."""

from __future__ import annotations

from collections.abc import Callable, Sequence

from torch import Tensor


class LazyFrames(Sequence):
    """frames[i] calls the i-th loader and returns its tensor; nothing is cached, so memory stays
    one frame."""

    def __init__(self, loaders: Sequence[Callable[[], Tensor]]):
        self._loaders = list(loaders)

    def __len__(self) -> int:
        return len(self._loaders)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return LazyFrames(self._loaders[index])
        return self._loaders[index]()

    def map(self, fn: Callable[[Tensor], Tensor]) -> LazyFrames:
        """The frames with `fn` applied to each as it is decoded."""
        return LazyFrames([_Mapped(loader, fn) for loader in self._loaders])


class _Mapped:
    def __init__(self, loader: Callable[[], Tensor], fn: Callable[[Tensor], Tensor]):
        self.loader, self.fn = loader, fn

    def __call__(self) -> Tensor:
        return self.fn(self.loader())


def frames(items: Sequence[Tensor | Callable[[], Tensor]]) -> LazyFrames:
    """Decoded tensors and loaders alike, as one LazyFrames (a tensor is returned as it is)."""
    if isinstance(items, LazyFrames):
        return items
    return LazyFrames([item if callable(item) else _Given(item) for item in items])


class _Given:
    def __init__(self, value: Tensor):
        self.value = value

    def __call__(self) -> Tensor:
        return self.value

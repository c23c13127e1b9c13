"""Per-view arrays loaded on demand and kept in a bounded LRU cache, so memory does not grow with the frames.

A 7-Scenes scene has up to 7,000 mapping frames; its depth maps alone are 8.6 GB. Steps that visit
views many times (the plane optimization, the track builder, the depth check) read them through
:class:`ViewCache`, which rebuilds an evicted entry from the view's files. Loading is deterministic,
so results do not depend on the cache size.
"""
from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping
from typing import Callable, Iterator, Sequence

DEFAULT_CAPACITY = 256  # views: ~300 MB of 640x480 float32 depth, ~350 MB of 320x240 plane targets


class LRU:
    """A least-recently-used cache of at most ``capacity`` entries, filled by ``load(key)`` on a miss."""

    def __init__(self, load: Callable, capacity: int = DEFAULT_CAPACITY):
        if capacity < 1:
            raise ValueError(f"cache capacity must be >= 1, got {capacity}")
        self.load = load
        self.capacity = int(capacity)
        self._items: OrderedDict = OrderedDict()
        self.hits = self.misses = 0

    def __call__(self, key):
        if key in self._items:
            self._items.move_to_end(key)
            self.hits += 1
            return self._items[key]
        self.misses += 1
        value = self.load(key)
        self._items[key] = value
        if len(self._items) > self.capacity:
            self._items.popitem(last=False)
        return value

    def __len__(self) -> int:
        return len(self._items)

    def clear(self) -> None:
        """Drop every entry (the counts stay)."""
        self._items.clear()

    def stats(self) -> dict:
        return {"capacity": self.capacity, "hits": self.hits, "misses": self.misses}


class ViewCache(Mapping):
    """A read-only ``{view name: array}`` over ``views`` whose values ``load(view)`` makes on first use.

    Views for which ``load`` is not possible (``has(view)`` false, e.g. no depth map) are not keys.
    """

    def __init__(self, views: Sequence, load: Callable, capacity: int = DEFAULT_CAPACITY,
                 has: Callable = lambda view: True):
        self._views = {v.name: v for v in views if has(v)}
        self._lru = LRU(lambda name: load(self._views[name]), capacity)

    def __getitem__(self, name: str):
        if name not in self._views:
            raise KeyError(name)
        return self._lru(name)

    def __iter__(self) -> Iterator[str]:
        return iter(self._views)

    def __len__(self) -> int:
        return len(self._views)

    def stats(self) -> dict:
        return self._lru.stats()


def depth_maps(views: Sequence, capacity: int = DEFAULT_CAPACITY) -> ViewCache:
    """Registered metric depth ``{view name: (H, W) float32}`` of the views that have depth, loaded on demand."""
    return ViewCache(views, lambda v: v.load_depth(), capacity, has=lambda v: v.depth_path is not None)


__all__ = ["LRU", "ViewCache", "depth_maps", "DEFAULT_CAPACITY"]

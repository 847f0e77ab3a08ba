"""A map's per-image working data, kept within a byte budget.

Comparing a frame with a map image needs that image's descriptors in a prepared form: unit
float vectors for XFeat (256 B per feature, 4x the stored int8 codes), the uint8 codes with
their norms and packed GEMM operand for RootSIFT. They are made on first use and kept, so a
map image costs its preparation once. Kept without a bound they grow with the area the fleet
has visited: on a map of both feature types about 350 kB per image beyond the mapped file
(433 images: +227 MB of RSS, 75 MB of it the file), so a 40,000-image map would end at some
14 GB. This cache keeps
the most recently used images within ``limit_bytes`` and makes an evicted image again when it
is next needed (a fraction of a millisecond; the result is the same, so estimates are too).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any, TypeVar

T = TypeVar("T")

DEFAULT_LIMIT_BYTES = 512 * 2**20  # per map: all of a ~1,000-image map of both types


def nbytes_of(value: Any) -> int:
    """Bytes held by a cached value: an array's, or the sum over a dataclass's arrays."""
    if hasattr(value, "nbytes"):
        return int(value.nbytes)
    fields = getattr(value, "__dict__", None) or {}
    return sum(int(getattr(v, "nbytes", 0)) for v in fields.values())


class ImageCache:
    """Least-recently-used values by key (``(kind, image_id)``) within ``limit_bytes``;
    thread-safe. A value larger than the whole budget is returned without being kept."""

    def __init__(self, limit_bytes: int = DEFAULT_LIMIT_BYTES) -> None:
        if limit_bytes < 0:
            raise ValueError(f"an image cache budget must be >= 0 bytes, got {limit_bytes}")
        self.limit_bytes = limit_bytes
        self.bytes = 0
        self.made = 0  # values made (first use or after eviction)
        self._items: OrderedDict[Hashable, tuple[Any, int]] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._items)

    def keys(self) -> list[Hashable]:
        """The keys kept, least recently used first."""
        with self._lock:
            return list(self._items)

    def get(self, key: Hashable, make: Callable[[], T]) -> T:
        """The value kept for ``key``, else ``make()`` (outside the lock: two threads may
        make the same value once each, and both get equal values)."""
        with self._lock:
            hit = self._items.get(key)
            if hit is not None:
                self._items.move_to_end(key)
                return hit[0]
        value = make()
        size = nbytes_of(value)
        with self._lock:
            self.made += 1
            if key in self._items or size > self.limit_bytes:
                return value
            self._items[key] = (value, size)
            self.bytes += size
            while self.bytes > self.limit_bytes:
                _, (_, old) = self._items.popitem(last=False)
                self.bytes -= old
        return value

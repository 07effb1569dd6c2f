"""Large scratch arrays kept between rasterizer calls instead of allocated afresh each time.

The CPU rasterizer's forward keeps every shaded (slot, pixel) pair for its backward, with room for
each slot's whole pixel rect: ~130 MB for the `cpu` preset's Stage-II batch (10 views at 320x240,
15k splats). Allocations that large are fresh mmap'd pages on every call, which the compositing
threads then fault in and zero while they work, which slowed the forward compositing
(benchmarks/results/rasterizer.md). A buffer handed back when its user is done (the backward) serves the next call.
"""

from __future__ import annotations

import threading

import numpy as np

# Room added when a buffer must grow, so that the slowly changing sizes of one training run stop
# reallocating after a few calls.
_GROWTH = 1.25
# Larger buffers are not kept: a long-running service should not hold a one-off giant render's memory (the `cpu`
# preset's Stage-II pairs take ~130 MB).
MAX_KEPT_BYTES = 1 << 30


class ScratchPool:
    """One free buffer per key; `take` lends it out (or allocates), `give` returns it.

    A buffer is only ever in one caller's hands: taken buffers leave the pool, and one that is never
    given back (or is larger than `max_kept_bytes`) is simply freed with its last reference. Thread-safe.
    """

    def __init__(self, max_kept_bytes: int = MAX_KEPT_BYTES) -> None:
        self._free: dict[str, np.ndarray] = {}
        self._lock = threading.Lock()
        self.max_kept_bytes = max_kept_bytes

    def take(self, key: str, size: int, dtype: np.dtype | type) -> np.ndarray:
        """A 1-D array of `size` elements of `dtype` with undefined contents."""
        dtype = np.dtype(dtype)
        with self._lock:
            buffer = self._free.pop(key, None)
        if buffer is None or buffer.dtype != dtype or buffer.shape[0] < size:
            buffer = np.empty(int(size * _GROWTH) + 1, dtype)
        return buffer[:size]

    def give(self, key: str, array: np.ndarray) -> None:
        """Returns an array from `take` (its caller must not use it afterwards); the larger buffer is kept."""
        buffer = array if array.base is None else array.base
        if buffer.nbytes > self.max_kept_bytes:
            return
        with self._lock:
            kept = self._free.get(key)
            if kept is None or kept.nbytes < buffer.nbytes:
                self._free[key] = buffer

    def clear(self) -> None:
        """Frees every kept buffer."""
        with self._lock:
            self._free.clear()

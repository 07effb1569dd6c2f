"""Parallel-for over numba kernels on plain threads.

numba's own `prange` runs on a second OpenMP runtime beside torch's, and both spin-wait at barriers:
on a 2-core machine torch's workers, still spinning after each torch op, starved numba's and a
forward+backward at 20k Gaussians went from ~50 ms to a ~500 ms median. Plain threads running
`nogil` kernels block instead of spinning, and kernels without parfor lowering compile ~3x faster.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import torch

_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_pool_lock = threading.Lock()


def num_threads() -> int:
    """Threads the rasterizer uses: torch's intra-op thread count, so one setting governs both."""
    return max(1, torch.get_num_threads())


def _executor(workers: int) -> ThreadPoolExecutor:
    global _pool, _pool_size
    with _pool_lock:
        if _pool is None or _pool_size < workers:
            _pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="cadsplat-render")
            _pool_size = workers
        return _pool


def parallel_for(kernel: Callable[..., None], n: int, *args, grain: int = 1) -> None:
    """Runs kernel(lo, hi, *args) over contiguous parts of range(n), one per thread.

    The calling thread takes the first part. Parts have at least `grain` items, so small inputs run
    on the calling thread alone; the split never changes results, since kernels write disjoint outputs.
    """
    parts = max(1, min(num_threads(), n // max(1, grain)))
    if parts == 1:
        kernel(0, n, *args)
        return
    bounds = [i * n // parts for i in range(parts + 1)]
    pool = _executor(parts - 1)
    futures = [pool.submit(kernel, bounds[i], bounds[i + 1], *args) for i in range(1, parts)]
    kernel(bounds[0], bounds[1], *args)
    for future in futures:
        future.result()

"""Parallel-for over numba kernels on plain threads, with dynamic scheduling.

Why not numba's `prange`: it runs on a second OpenMP runtime beside torch's, whose workers also
spin-wait between parallel regions, so on a 2-core machine the two pools took turns starving each
other; parfor lowering also tripled the kernels' cold compile time. Plain threads running `nogil`
kernels sleep when idle. Work is cut into a few parts per thread, taken in order by whichever thread
is free, so a thread that loses its core for a while only delays its current part.

torch's own OpenMP workers still spin after each op unless OMP_WAIT_POLICY=PASSIVE is set before torch
is imported (the `cadsplat` command and the benchmarks set it): even on a quiet 2-core machine their
spinning took the cores these threads need (rig scene clamp, `preview`: 12.7 s under libgomp's
default, 10.5-10.8 s with PASSIVE; on a busy machine 3-10x).
"""

from __future__ import annotations

import itertools
import os
import sys
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

PARTS_PER_THREAD = 4

_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_pool_lock = threading.Lock()


def num_threads() -> int:
    """Threads the kernels use: torch's intra-op thread count once torch is loaded, so one setting governs
    both; before that (registration alone does not need torch) the CPUs this process may run on."""
    torch = sys.modules.get("torch")
    if torch is not None:
        return max(1, torch.get_num_threads())
    affinity = getattr(os, "sched_getaffinity", None)
    return max(1, len(affinity(0)) if affinity else (os.cpu_count() or 1))


def _forget_pool() -> None:
    """A forked child inherits the pool object but none of its threads: start afresh there."""
    global _pool, _pool_size, _pool_lock
    _pool, _pool_size, _pool_lock = None, 0, threading.Lock()


os.register_at_fork(after_in_child=_forget_pool)


def _executor(workers: int) -> ThreadPoolExecutor:
    global _pool, _pool_size
    with _pool_lock:
        if _pool is None or _pool_size < workers:
            _pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="cadsplat-render")
            _pool_size = workers
        return _pool


def parallel_for(kernel: Callable[..., None], n: int, *args, grain: int = 1) -> None:
    """Runs kernel(lo, hi, *args) over contiguous parts of range(n) on up to `num_threads()` threads.

    Parts have at least `grain` items (small inputs run on the calling thread alone) and are handed
    out in order to whichever thread is free. Kernels write disjoint outputs per index, so neither
    the split nor the schedule changes results.
    """
    threads = num_threads()
    parts = max(1, min(threads * PARTS_PER_THREAD, n // max(1, grain)))
    if parts == 1 or threads == 1:
        kernel(0, n, *args)
        return
    bounds = [i * n // parts for i in range(parts + 1)]
    counter = itertools.count()  # next() is atomic under the GIL

    def worker() -> None:
        while (i := next(counter)) < parts:
            kernel(bounds[i], bounds[i + 1], *args)

    futures = [_executor(threads - 1).submit(worker) for _ in range(min(threads, parts) - 1)]
    try:
        worker()
    finally:
        for future in futures:
            future.result()

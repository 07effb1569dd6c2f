"""Parallel-for over numba kernels on plain threads, with dynamic scheduling.

Why not numba's `prange`: it runs on a second OpenMP runtime beside torch's, whose workers also
spin-wait between parallel regions, so on a machine of few cores the two pools took turns starving
each other; parfor lowering also lengthened the kernels' cold compile (benchmarks/results/rig_scenes.md).
Plain threads running `nogil` kernels sleep when idle. Work is cut into a few parts per thread, taken in order by whichever thread
is free, so a thread that loses its core for a while only delays its current part.

torch's own OpenMP workers spin after each op before they sleep, for libgomp's default ~3 ms: on a machine of
few cores that spinning takes the cores these threads need (measured: benchmarks/results/rig_scenes.md).
`configure_openmp` shortens it before torch is imported.
"""

from __future__ import annotations

import itertools
import os
import sys
import threading
from collections.abc import Callable

PARTS_PER_THREAD = 4

# Spins (libgomp reckons ~100 per microsecond) an idle OpenMP worker makes before it sleeps. ~0.1 ms bridges the gap
# between a training step's back-to-back torch ops, which otherwise pay a futex wake-up each; beside a busy
# neighbour the spin costs time instead (both measured: benchmarks/results/rig_scenes.md). An appliance
# reconstructs alone; a machine shared with other work sets OMP_WAIT_POLICY=PASSIVE.
OPENMP_SPIN_COUNT = 10_000


def configure_openmp(environ: dict | None = None) -> None:
    """Before torch loads: idle OpenMP workers spin `OPENMP_SPIN_COUNT` times, then sleep, unless the user chose a
    wait policy or a spin count. libgomp reads them once, when torch's library loads: called after that, only the
    processes this one starts see the change."""
    environ = os.environ if environ is None else environ
    if "OMP_WAIT_POLICY" not in environ and "GOMP_SPINCOUNT" not in environ:
        environ["GOMP_SPINCOUNT"] = str(OPENMP_SPIN_COUNT)


def openmp_wait(environ: dict | None = None) -> str:
    """How idle OpenMP workers wait in `environ`, as a benchmark reports it: "GOMP_SPINCOUNT=10000"."""
    environ = os.environ if environ is None else environ
    chosen = [f"{k}={environ[k]}" for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT") if k in environ]
    return ", ".join(chosen) or "libgomp's default wait"


class _Team:
    """Helper threads that run one parallel-for at a time beside the calling thread.

    Each helper sleeps on its own lock and reports on another: a handful of C-level lock operations per call
    where a `ThreadPoolExecutor` future costs more (benchmarks/results/rasterizer.md); the rasterizer makes 8 such
    calls per training step.
    """

    def __init__(self) -> None:
        self.busy = threading.Lock()  # held by the one caller the team is serving
        self._wake: list[threading.Lock] = []
        self._done: list[threading.Lock] = []
        self._task: Callable[[], None] | None = None
        self._errors: list[BaseException | None] = []

    def run(self, task: Callable[[], None], helpers: int) -> None:
        """task() on the calling thread and on `helpers` helper threads; re-raises the first error. Call with `busy`.

        Every helper woken is waited for, even through a KeyboardInterrupt (raised once they are done): a helper
        left running would report "done" to a later call, which would then return before its outputs are written.
        """
        while len(self._wake) < helpers:
            self._start_helper()
        self._task = task
        woken = 0
        try:
            for i in range(helpers):
                self._wake[i].release()
                woken = i + 1
            task()
        finally:
            interrupted = None
            for i in range(woken):
                while True:
                    try:
                        self._done[i].acquire()
                        break
                    except BaseException as error:
                        interrupted = interrupted or error
            self._task = None
            errors = [error for error in self._errors[:helpers] if error is not None]
            self._errors[:helpers] = [None] * helpers
            if interrupted is not None:
                raise interrupted
        if errors:
            raise errors[0]

    def _start_helper(self) -> None:
        i = len(self._wake)
        wake, done = threading.Lock(), threading.Lock()
        wake.acquire()
        done.acquire()
        # Listed only once the thread runs: a thread that fails to start must not be waited for.
        threading.Thread(target=self._serve, args=(i, wake, done), name=f"cadsplat-render-{i}", daemon=True).start()
        self._wake.append(wake)
        self._done.append(done)
        self._errors.append(None)

    def _serve(self, i: int, wake: threading.Lock, done: threading.Lock) -> None:
        while True:
            wake.acquire()
            try:
                self._task()
            except BaseException as error:  # handed to the caller, which re-raises it
                self._errors[i] = error
            finally:
                done.release()


_team = _Team()


def num_threads() -> int:
    """Threads the kernels use: torch's intra-op thread count once torch is loaded, so one setting governs
    both; before that (registration alone does not need torch) the CPUs this process may run on."""
    torch = sys.modules.get("torch")
    if torch is not None:
        return max(1, torch.get_num_threads())
    affinity = getattr(os, "sched_getaffinity", None)
    return max(1, len(affinity(0)) if affinity else (os.cpu_count() or 1))


def _forget_team() -> None:
    """A forked child inherits the team object but none of its threads: start afresh there."""
    global _team
    _team = _Team()


os.register_at_fork(after_in_child=_forget_team)


def parallel_for(kernel: Callable[..., None], n: int, *args, grain: int = 1) -> None:
    """Runs kernel(lo, hi, *args) over contiguous parts of range(n) on up to `num_threads()` threads.

    Parts have at least `grain` items (small inputs run on the calling thread alone) and are handed
    out in order to whichever thread is free. Kernels write disjoint outputs per index, so neither
    the split nor the schedule changes results. While the helper threads serve one caller, another (a second Python
    thread, or a kernel that calls back in) runs its loop on its own thread.
    """
    threads = num_threads()
    parts = max(1, min(threads * PARTS_PER_THREAD, n // max(1, grain)))
    team = _team
    if parts == 1 or threads == 1 or not team.busy.acquire(blocking=False):
        kernel(0, n, *args)
        return
    try:
        bounds = [i * n // parts for i in range(parts + 1)]
        counter = itertools.count()  # next() is atomic under the GIL

        def worker() -> None:
            while (i := next(counter)) < parts:
                kernel(bounds[i], bounds[i + 1], *args)

        team.run(worker, min(threads, parts) - 1)
    finally:
        team.busy.release()

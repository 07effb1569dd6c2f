"""A filesystem fault injector for the appliance's write sites (tests and benchmarks.bench_faults).

Every file the appliance writes goes through `calibration.fileio._durable_temp` (atomic writes),
the store's reserve through `rig.store._allocate`, directories through `os.mkdir`, and the job
store through SQLite transactions (`deploy.jobs.JobStore._tx`). `FaultyDisk` wraps those for paths
under one root and fails them the way a filesystem does:

- `fail_at=N`: the N-th write under the root raises `errno_` (ENOSPC by default) once, or from
  then on with `persistent=True` (EROFS: the filesystem went read-only);
- `fill_at=N`: at the N-th write another process fills the disk: from then on a write that needs
  more than the space the appliance frees itself (its reserve) raises ENOSPC;
- `capacity=B`: a disk of B bytes (what `free_bytes` reports to the store).
"""

from __future__ import annotations

import errno
import os
import sqlite3
from contextlib import contextmanager
from pathlib import Path


def tree_bytes(root: Path) -> int:
    total = 0
    for dirpath, _, files in os.walk(root):
        for f in files:
            try:
                total += os.lstat(os.path.join(dirpath, f)).st_size
            except FileNotFoundError:
                pass
    return total


class FaultyDisk:
    def __init__(
        self,
        root: str | os.PathLike,
        *,
        fail_at: int | None = None,
        errno_: int = errno.ENOSPC,
        persistent: bool = False,
        fill_at: int | None = None,
        capacity: int | None = None,
    ) -> None:
        self.root = os.path.abspath(root)
        self.fail_at, self.errno, self.persistent, self.fill_at = fail_at, errno_, persistent, fill_at
        self.capacity = capacity
        self.calls: list[tuple[int, str, str]] = []
        self.faults = 0

    def _under(self, path) -> bool:
        return os.path.abspath(os.fspath(path)).startswith(self.root + os.sep) or os.path.abspath(os.fspath(path)) == self.root

    def free_bytes(self, _path=None) -> int:
        if self.capacity is None:
            return 1 << 40
        return max(0, self.capacity - tree_bytes(Path(self.root)))

    def _site(self, site: str, path, size: int) -> None:
        """Count one write under the root and raise the fault it is due."""
        n = len(self.calls) + 1
        self.calls.append((n, site, os.fspath(path)))
        if self.fill_at is not None and n == self.fill_at:
            self.capacity = tree_bytes(Path(self.root))
        if self.fail_at is not None and (n == self.fail_at or (self.persistent and n > self.fail_at)):
            self.faults += 1
            self._raise(path)
        if self.capacity is not None and size and tree_bytes(Path(self.root)) + size > self.capacity:
            self.faults += 1
            self._raise(path, errno.ENOSPC)

    def _raise(self, path, code: int | None = None):
        code = self.errno if code is None else code
        raise OSError(code, os.strerror(code), os.fspath(path))

    @contextmanager
    def active(self):
        import calibration.fileio as fio
        import deploy.jobs as jobs
        import rig.store as store

        real_temp, real_alloc, real_mkdir, real_tx = fio._durable_temp, store._allocate, os.mkdir, jobs.JobStore._tx
        disk = self

        def durable_temp(path, data):
            if disk._under(path):
                disk._site("write", path, len(data))
            return real_temp(path, data)

        def allocate(path, size):
            if disk._under(path):
                disk._site("reserve", path, size)
            return real_alloc(path, size)

        def mkdir(path, mode=0o777, *a, **kw):
            if disk._under(path):
                disk._site("mkdir", path, 0)
            return real_mkdir(path, mode, *a, **kw)

        @contextmanager
        def tx(self_):
            if disk._under(self_.path):
                try:
                    disk._site("sqlite", self_.path, 4096)
                except OSError as e:
                    raise sqlite3.OperationalError(
                        "database or disk is full" if e.errno == errno.ENOSPC else "attempt to write a readonly database"
                    ) from e
            with real_tx(self_) as db:
                yield db

        fio._durable_temp, store._allocate, os.mkdir, jobs.JobStore._tx = durable_temp, allocate, mkdir, tx
        try:
            yield self
        finally:
            fio._durable_temp, store._allocate, os.mkdir, jobs.JobStore._tx = real_temp, real_alloc, real_mkdir, real_tx

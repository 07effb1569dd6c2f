"""Guards at the edges: one writer per directory, and paths read from documents kept inside their folder.

`hold_lock` is an advisory `flock` held for a process's life, so a second rig, service or import on
the same store or work directory is refused in one sentence naming the holder. `contained` resolves a
path a document names (a capture's `file_path`, a library's mesh `file`) and refuses one that leaves
the document's folder, by `..`, an absolute path or a symbolic link.
"""

from __future__ import annotations

import errno
import fcntl
import os
from pathlib import Path


class LockHeld(RuntimeError):
    """Another live process holds the lock; the message names it and its pid."""


class PathOutside(ValueError):
    """A document names a path outside its own folder."""


class ProcessLock:
    """An exclusive (or shared) advisory lock on `path`, held from `acquire` until `release` or the process ends.

    The kernel drops a flock when its holder dies, so a crashed holder never leaves a stale lock; the
    file keeps the last holder's pid and role only to name it in the refusal.
    """

    def __init__(self, path: str | os.PathLike, role: str, *, shared: bool = False):
        self.path = Path(path)
        self.role = role
        self.shared = shared
        self._fd: int | None = None

    def acquire(self) -> ProcessLock:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, (fcntl.LOCK_SH if self.shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except OSError as e:
            holder = os.pread(fd, 256, 0).decode(errors="replace").strip() or "another process"
            os.close(fd)
            if e.errno in (errno.EWOULDBLOCK, errno.EACCES):
                raise LockHeld(f"{self.path.parent} is in use by {holder}; stop it first or use another directory") from None
            raise
        if not self.shared:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{self.role} (pid {os.getpid()})".encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the last descriptor drops the flock
            self._fd = None

    def __enter__(self) -> ProcessLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def hold_lock(directory: str | os.PathLike, role: str, *, name: str = ".lock", shared: bool = False) -> ProcessLock:
    """Take `directory`/`name` for this process (exclusive unless `shared`); raises LockHeld naming the holder."""
    return ProcessLock(Path(directory) / name, role, shared=shared).acquire()


def contained(root: str | os.PathLike, relative: str | os.PathLike, *, what: str = "path") -> Path:
    """`root`/`relative`, resolved, if it stays inside `root` (symbolic links followed); raises PathOutside otherwise.

    root: the folder of the document that names the path (a capture, a library, a twin)
    relative: the path as the document gives it
    """
    base = Path(root).resolve()
    rel = Path(relative)
    if rel.is_absolute():
        raise PathOutside(f"{what} {str(relative)!r} is absolute; it must be relative to {base}")
    target = (base / rel).resolve()
    if target != base and base not in target.parents:
        raise PathOutside(f"{what} {str(relative)!r} leads outside {base}")
    return target

"""Where numba keeps this package's compiled kernels: a directory named after the package's sources.

numba caches each `cache=True` kernel with the modification time and size of its own source file, and
nothing of the files its callees live in. A kernel that calls one from another module (registration's
silhouette scorer inlines `silhouette.fill_triangles`) kept running the callee it was compiled with after
that module changed: an appliance updated in place would score with old code and say nothing. Keyed on a
hash of every source file of the package, any change compiles afresh, and an unchanged package loads what
it compiled before.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent
# The cache `configure` chose, handed to child processes beside NUMBA_CACHE_DIR so they do not nest another in it.
ENV = "CADSPLAT_KERNEL_CACHE"
# Directories of other source versions are removed once unused for this long: a process still running the
# old code recompiles what it misses, and a day covers any reconstruction.
STALE_AFTER_S = 86_400.0


def source_hash(package: Path = PACKAGE) -> str:
    """16 hex digits of SHA-256 over the relative paths and contents of every .py file under `package`."""
    digest = hashlib.sha256()
    for path in sorted(package.rglob("*.py")):
        digest.update(path.relative_to(package).as_posix().encode())
        digest.update(b"\0")
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def cache_root(environ: dict, package: Path = PACKAGE) -> Path:
    """The directory that holds one kernel cache per source version: the parent process's choice, else inside the
    user's NUMBA_CACHE_DIR when set, else the package's __pycache__ when writable (an editable install), else
    $XDG_CACHE_HOME (~/.cache, or the temporary directory for a user without a home)/cadsplat."""
    chosen = environ.get(ENV)
    if chosen and environ.get("NUMBA_CACHE_DIR") == chosen:
        return Path(chosen).parent
    if environ.get("NUMBA_CACHE_DIR"):
        return Path(environ["NUMBA_CACHE_DIR"]) / "cadsplat"
    if os.access(package, os.W_OK):
        return package / "__pycache__" / "numba"
    home = os.path.expanduser("~")  # left as "~" when there is none (a service user); Path.home() would raise
    base = environ.get("XDG_CACHE_HOME") or (os.path.join(home, ".cache") if home != "~" else tempfile.gettempdir())
    return Path(base) / "cadsplat" / "numba"


def prune(root: Path, keep: Path, now: float, stale_after_s: float = STALE_AFTER_S) -> list[Path]:
    """Removes the caches under `root` other than `keep` that nothing has written for `stale_after_s`; returns them."""
    removed = []
    for other in root.iterdir() if root.is_dir() else ():
        if other != keep and other.is_dir() and now - other.stat().st_mtime > stale_after_s:
            shutil.rmtree(other, ignore_errors=True)
            removed.append(other)
    return removed


def configure(environ: dict | None = None, package: Path = PACKAGE) -> Path:
    """Points numba's cache at this source version's directory in `environ` (default: this process's, and then numba
    too, loaded or not); returns it."""
    environ = os.environ if environ is None else environ
    root = cache_root(environ, package)
    path = root / source_hash(package)
    if not path.is_dir():
        try:
            path.mkdir(parents=True, exist_ok=True)
            prune(root, path, time.time())
        except OSError:
            pass  # numba cannot use it and falls back on its own cache locations, or compiles in memory
    environ["NUMBA_CACHE_DIR"] = environ[ENV] = str(path)
    numba = sys.modules.get("numba")
    if environ is os.environ and numba is not None:
        # numba read the variable when it loaded; kernels decorated from now on take the attribute.
        numba.config.CACHE_DIR = str(path)
    return path

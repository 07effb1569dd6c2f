import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numba

from reconstruction import kernel_cache
from reconstruction.kernel_cache import ENV, cache_root, configure, prune, source_hash

CALLEE = "import numba\n\n@numba.njit(cache=True)\ndef value():\n    return {}\n"
CALLER = "import numba\nfrom pkg.callee import value\n\n@numba.njit(cache=True)\ndef read():\n    return value()\n"


def _package(root: Path, returned: int) -> Path:
    pkg = root / "pkg"
    pkg.mkdir(parents=True, exist_ok=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "callee.py").write_text(CALLEE.format(returned))
    if not (pkg / "caller.py").exists():
        (pkg / "caller.py").write_text(CALLER)
    return pkg


def _run(root: Path, keyed: bool) -> int:
    """The caller's result in a fresh process: kernels cached as numba keys them, or in `kernel_cache`'s directory."""
    code = textwrap.dedent(f"""
        import importlib.util, sys
        from pathlib import Path
        sys.path.insert(0, {str(root)!r})
        if {keyed}:
            spec = importlib.util.spec_from_file_location("kernel_cache", {kernel_cache.__file__!r})
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            module.configure(package=Path({str(root / "pkg")!r}))
        from pkg.caller import read
        print(read())
    """)
    env = {k: v for k, v in os.environ.items() if k != ENV}
    env["NUMBA_CACHE_DIR"] = str(root / "cache")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return int(out.stdout.strip().splitlines()[-1])


def test_a_changed_callee_is_compiled_again_where_numba_alone_serves_the_old_one(tmp_path):
    for keyed, after in ((False, 1), (True, 2)):
        root = tmp_path / ("keyed" if keyed else "plain_run")
        _package(root, 1)
        assert _run(root, keyed) == 1
        _package(root, 2)  # only the callee's file changes
        assert _run(root, keyed) == after


def test_the_hash_follows_every_source_file_and_nothing_else(tmp_path):
    pkg = _package(tmp_path, 1)
    first = source_hash(pkg)
    (pkg / "notes.txt").write_text("not a source")
    assert source_hash(pkg) == first
    _package(tmp_path, 2)
    assert source_hash(pkg) != first
    _package(tmp_path, 1)
    assert source_hash(pkg) == first


def test_this_process_compiles_into_this_source_versions_cache():
    from reconstruction.silhouette import fill_triangles

    path = Path(numba.config.CACHE_DIR)
    assert path.name == source_hash() and os.environ["NUMBA_CACHE_DIR"] == str(path)
    assert Path(fill_triangles._cache._cache_path).is_relative_to(path)


def test_a_users_cache_dir_holds_ours_and_a_child_process_does_not_nest_another(tmp_path):
    pkg = _package(tmp_path, 1)
    environ = {"NUMBA_CACHE_DIR": str(tmp_path / "user")}
    path = kernel_cache.configure(environ, package=pkg)
    assert path == tmp_path / "user" / "cadsplat" / source_hash(pkg) and path.is_dir()
    child = dict(environ)  # what a subprocess inherits
    assert cache_root(child, pkg) == path.parent
    assert kernel_cache.configure(child, package=pkg) == path


def test_prune_removes_other_versions_left_unused_for_a_day(tmp_path):
    keep, recent, old = (tmp_path / name for name in ("keep", "recent", "old"))
    for d in (keep, recent, old):
        d.mkdir()
    now = old.stat().st_mtime + 2 * kernel_cache.STALE_AFTER_S
    os.utime(keep, (now - 3 * kernel_cache.STALE_AFTER_S,) * 2)
    os.utime(recent, (now - 60.0,) * 2)
    assert prune(tmp_path, keep, now) == [old]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep", "recent"]


def test_an_unwritable_cache_root_still_runs_the_kernels(tmp_path):
    root = tmp_path / "blocked"
    _package(root, 1)
    (root / "cache").write_text("")  # a file where the cache directory should go
    path = configure({"NUMBA_CACHE_DIR": str(root / "cache")}, package=root / "pkg")
    assert not path.exists()
    assert _run(root, keyed=True) == 1


def test_an_installed_package_caches_in_the_users_cache_or_the_temporary_directory(tmp_path, monkeypatch):
    pkg = _package(tmp_path, 1)
    monkeypatch.setattr(kernel_cache.os, "access", lambda path, mode: False)  # site-packages, read-only
    assert cache_root({"XDG_CACHE_HOME": str(tmp_path / "xdg")}, pkg) == tmp_path / "xdg" / "cadsplat" / "numba"
    monkeypatch.setattr(kernel_cache.os.path, "expanduser", lambda path: path)  # a service user without a home
    assert cache_root({}, pkg) == Path(kernel_cache.tempfile.gettempdir()) / "cadsplat" / "numba"

"""The install-time warmup compiles every kernel a library build, a reconstruction and an inspection ask for."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

from reconstruction.kernel_cache import ENV
from tests.conftest import REPO

# A library build, a reconstruction with every stage cut to two iterations, and an inspection of the bundled sample, in
# a fresh process; then the package's kernels that compiled instead of loading from the cache.
RUN = textwrap.dedent("""
    import gc, json, sys, tempfile
    from pathlib import Path
    import numba
    from deploy.inspection_report import inspect_twin_dir
    from reconstruction.library import build_library
    from reconstruction.pipeline import reconstruct_capture
    sample, work = Path(sys.argv[1]), Path(tempfile.mkdtemp())
    build_library(sample / "library_meshes", work / "library", progress=False, log=lambda _m: None)
    reconstruct_capture(sample / "train", work / "library", work / "twin", preset="cpu",
                overrides={"iters_pose": 2, "iters_deform": 2, "iters_photo": 2})
    inspect_twin_dir(work / "twin", work / "inspection", tolerance_mm=1.5, max_unseen_pct=50.0, turntable=2)
    ours = ("reconstruction", "calibration", "simulation", "deploy", "rig")
    compiled = sorted({f"{d.py_func.__module__}.{d.py_func.__name__}" for d in gc.get_objects()
                       if isinstance(d, numba.core.dispatcher.Dispatcher) and d.stats.cache_misses
                       and d.py_func.__module__.split(".")[0] in ours})
    print(json.dumps(compiled))
""")


def test_a_first_reconstruction_after_the_warmup_compiles_nothing(tmp_path):
    sample = REPO / "sample"
    env = {k: v for k, v in os.environ.items() if k != ENV}
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "cache")  # as a fresh install: nothing compiled yet
    subprocess.run([sys.executable, "-m", "reconstruction.warmup"], env=env, cwd=REPO, check=True, capture_output=True)
    out = subprocess.run([sys.executable, "-c", RUN, str(sample)], env=env, cwd=REPO, check=True, capture_output=True, text=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []

"""SIGKILL at random points of `rig watch` and `service run` (a few here; 100 each in benchmarks.bench_faults):
after each, every reported capture is committed and verifies, nothing published is half-written, and the
next start carries on."""

from __future__ import annotations

import random

import pytest

from tests.killing import cadsplat, job_statuses, reported, run_until_killed, store_after_kill, work_after_kill

SMALL = ["--views", "3", "--size", "96", "72", "--min-free-gb", "0"]


def test_rig_watch_killed_at_random_points_loses_no_reported_capture(tmp_path):
    store = tmp_path / "S"
    rng = random.Random(16)
    committed: list[str] = []
    for _ in range(3):
        out, killed = run_until_killed(
            cadsplat("rig", "watch", "--simulate", "--trigger", "can", "--rate", "6", "--store", str(store), *SMALL),
            rng.uniform(0.0, 1.5),
            ready=("reference", "committed"),
        )
        assert killed
        committed += reported(out)
        store_after_kill(store, committed)
    assert committed, "no capture was committed before the kills"
    assert (store / "references" / "v0001" / "reference.json").exists()


@pytest.mark.slow
def test_service_run_killed_at_random_points_finishes_every_job(tmp_path):
    from reconstruction.library import build_library
    from tests.conftest import REPO

    store, work, lib = tmp_path / "S", tmp_path / "W", tmp_path / "L"
    out, _ = run_until_killed(
        cadsplat("rig", "watch", "--simulate", "--trigger", "can", "--rate", "4", "--max-captures", "1", "--store", str(store), *SMALL), 300
    )
    assert len(reported(out)) == 1
    build_library(REPO / "sample" / "library_meshes", lib, progress=False, log=lambda _m: None)
    run = cadsplat(
        "service",
        "run",
        "--store",
        str(store),
        "--work",
        str(work),
        "--library",
        str(lib),
        "--preset",
        "preview",
        "--poll",
        "0.2",
        "--min-free-gb",
        "0",
        "--max-jobs",
        "1",
    )
    rng = random.Random(16)
    for _ in range(2):
        run_until_killed(run, rng.uniform(3.0, 12.0))
        work_after_kill(work)  # raises if a published twin or export is half-written
    out, killed = run_until_killed(run, 600)
    assert not killed and "job-done" in out, out
    assert job_statuses(work) == ["done"]
    final = work_after_kill(work)
    assert final["twins"] == 1 and final["exports"] == 3 and final["leftovers"] == 0

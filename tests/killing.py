"""SIGKILL at a random point of `cadsplat rig watch` or `cadsplat service run`, and what must hold after
(tests/deploy/test_kill_appliance.py and benchmarks.bench_faults share it)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def cadsplat(*args: str) -> list[str]:
    return [sys.executable, "-c", "import sys; from deploy.cli import main; sys.exit(main())", *args]


def run_until_killed(
    argv: list[str], kill_after_s: float, *, ready: tuple[str, ...] | None = None, timeout_s: float = 600
) -> tuple[str, bool]:
    """Run `argv`; SIGKILL it `kill_after_s` after it printed a line starting with one of `ready` (or after start).
    Returns (stdout, killed)."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env, cwd=REPO)
    lines: list[str] = []
    start = time.monotonic()
    if ready is not None:
        for line in proc.stdout:
            lines.append(line)
            if line.startswith(ready) or time.monotonic() - start > timeout_s:
                break
    try:
        out, _ = proc.communicate(timeout=kill_after_s)
        return "".join(lines) + out, False
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGKILL)
        out, _ = proc.communicate(timeout=60)
        return "".join(lines) + out, True


def reported(stdout: str, word: str = "committed") -> list[str]:
    return [line.split()[1] for line in stdout.splitlines() if line.startswith(word + " ")]


def store_after_kill(store: Path, committed: list[str]) -> dict:
    """Reopen the store as the next start does; every reported capture must be there and verify, every
    quarantine entry must say why, nothing may stay half-written. Returns counts; raises AssertionError."""
    from deploy.commands.store import verify_store
    from rig.store import CaptureStore

    reopened = CaptureStore(store, min_free_bytes=0)
    counts, problems = verify_store(store)
    assert not problems, problems
    present = set(reopened.capture_ids())
    missing = sorted(set(committed) - present)
    assert not missing, f"reported committed but not in the store: {missing}"
    return {"captures": counts["verified"], "quarantined": counts["quarantined"], "recovered": len(reopened.recovered)}


def work_after_kill(work: Path) -> dict:
    """Every published output of the service is whole: each twin verifies against its manifest and each
    export reads. Half-assembled `.incoming`/`.tmp` leftovers are counted (the next start removes them)."""
    from reconstruction.twin import load_twin

    twins = exports = 0
    jobs = work / "jobs"
    for job in sorted(jobs.iterdir()) if jobs.is_dir() else []:
        if (job / "twin").exists():
            load_twin(job / "twin")
            twins += 1
        for out in sorted((job / "export").iterdir()) if (job / "export").is_dir() else []:
            if out.name.startswith("."):
                continue
            if out.suffix == ".ply":
                from reconstruction.twin import read_splats_ply

                read_splats_ply(out)
            elif out.suffix == ".glb":
                from simulation.gltf_splats import accessor_array, read_glb

                doc, blob = read_glb(out.read_bytes())  # the splats' KHR_gaussian_splatting primitive, whole
                positions = accessor_array(doc, blob, doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"])
                assert len(positions) > 0, f"{out}: a GLB without splats"
            else:
                assert (out / "model.xml").is_file(), f"{out}: an export directory without its model.xml"
            exports += 1
    leftovers = [p for p in work.rglob(".*") if p.name.endswith((".incoming", ".tmp"))]
    return {"twins": twins, "exports": exports, "leftovers": len(leftovers)}


def job_statuses(work: Path) -> list[str]:
    from deploy.jobs import JobStore

    store = JobStore(work / "jobs.sqlite")
    try:
        return [j.status for j in store.jobs()]
    finally:
        store.close()


def capture_meta(store: Path, capture_id: str) -> dict:
    return json.loads((store / "captures" / capture_id / "transforms.json").read_text())["cadsplat"]

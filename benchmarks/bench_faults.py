"""Fault injection over the appliance, with counts: `python -m benchmarks.bench_faults [--kills N]`.

1. ENOSPC (once; and "another process fills the disk") and EROFS (read-only from that site on, then
   writable again before one more trigger; and read-only until the rig stops, its held captures
   spilled and imported on the next start) at every write site of the capture store (a reference +
   3 captures on pattern cameras), the calibration keeper and the service (one run per site,
   tests.faultfs.FaultyDisk wrapping the write sites).
2. SIGKILL at N random points of `cadsplat rig watch --simulate` (one store, restarted after each kill).
3. SIGKILL at N random points of `cadsplat service run` (preview preset) on 2 simulated captures, then
   one uninterrupted run to the end.
4. One writer per store: a second rig on a store `rig watch` holds; `store import-spill` during
   `rig watch`; `store verify` during `rig watch` (`--parts two-writers,import-during-watch,verify-during-watch`).
5. (`--parts bomb`) PNG decompression bombs in a capture through `cadsplat register`: refused in one
   sentence, with the process's peak RSS (os.wait4's rusage), beside what decoding the bomb costs.
6. A poison job (`--parts poison`): a capture whose register step SIGKILLs the service (as the OOM killer
   does), first in a queue of three, the service restarted after each death as systemd's Restart= does.

After each fault it checks what the acceptance asks: every capture committed and verifying or refused
and counted, 0 lost, 0 half-written outputs, one sentence per failure. Writes a markdown table to
benchmarks/results/faults.md.
"""

from __future__ import annotations

import argparse
import errno
import os
import random
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks._common import RESULTS
from tests.deploy.test_faults import _captures, _keeper_flow, _run_rig, _Steps, spill_of
from tests.faultfs import FaultyDisk
from tests.killing import REPO, cadsplat, job_statuses, reported, run_until_killed, store_after_kill, work_after_kill

TRIGGERS = 3  # captures per write-site run, after the reference


def one_sentence(text: str) -> bool:
    return bool(text) and "\n" not in text and "Traceback" not in text


def rig_sweep(tmp: Path, mode: str) -> dict:
    from deploy.commands.store import verify_store
    from rig.store import CaptureStore

    count = FaultyDisk(tmp / f"{mode}-count")
    _run_rig(tmp / f"{mode}-count", count, triggers=TRIGGERS)
    sites = len(count.calls)
    tally = {
        "sites": sites,
        "triggers": 0,
        "committed": 0,
        "of_which_held_then_written": 0,
        "refused": 0,
        "quarantined": 0,
        "spilled": 0,
        "imported_at_next_start": 0,
        "failed": 0,
        "lost": 0,
        "half_written": 0,
        "not_one_sentence": 0,
    }
    for n in range(1, sites + 1):
        root = tmp / f"{mode}-{n}"
        disk = {
            "enospc": lambda: FaultyDisk(root, fail_at=n),
            "filled": lambda: FaultyDisk(root, fill_at=n),
            "erofs": lambda: FaultyDisk(root, fail_at=n, errno_=errno.EROFS, persistent=True),  # then writable again
            "erofs-until-stop": lambda: FaultyDisk(root, fail_at=n, errno_=errno.EROFS, persistent=True),
        }[mode]()
        outs, _ = _run_rig(root, disk, heal=mode == "erofs", triggers=TRIGGERS)
        for o in outs[1:]:
            if o.status == "held":
                continue
            tally["of_which_held_then_written"] += o.status == "committed" and o.reason.startswith("written after")
            tally["triggers"] += 1
            tally[o.status if o.status in tally else "failed"] += 1
            tally["lost"] += o.status == "failed"
            tally["not_one_sentence"] += o.status != "committed" and not one_sentence(o.reason)
        imported, problem = CaptureStore(root, min_free_bytes=0).import_spill(spill_of(root))  # the next start
        tally["imported_at_next_start"] += sum(r.status == "committed" for r in imported)
        tally["not_one_sentence"] += bool(problem) and not one_sentence(problem)
        counts, problems = verify_store(root, spill_of(root).root)  # a capture still waiting in the spill is a problem too
        stored = {o.capture_id for o in outs if o.status in ("committed", "spilled")}
        tally["lost"] += len(stored - set(p.name for p in (root / "captures").iterdir()))
        tally["half_written"] += len(problems)
    return tally


def keeper_sweep(tmp: Path) -> dict:
    from calibration.calibfile import CalibrationStore

    (tmp / "k-count").mkdir()
    count = FaultyDisk(tmp / "k-count")
    with count.active():
        _keeper_flow(tmp / "k-count")
    tally = {"sites": len(count.calls), "unreadable_calibration": 0, "half_written": 0, "not_one_sentence": 0}
    for n in range(1, len(count.calls) + 1):
        root = tmp / f"k{n}"
        root.mkdir()
        with FaultyDisk(root, fail_at=n).active():
            try:
                _keeper_flow(root)
            except OSError as e:
                tally["not_one_sentence"] += not one_sentence(str(e))
        tally["half_written"] += sum(1 for p in root.rglob("*") if p.name.endswith(".tmp"))
        store = CalibrationStore(root / "calibration.json")
        try:
            if (root / "calibration.json").exists():
                store.load()
            for v in store.versions():
                store.load(v)
        except ValueError:
            tally["unreadable_calibration"] += 1
    return tally


def service_sweep(tmp: Path) -> dict:
    from deploy.service import PipelineService

    _captures(tmp / "svc-store")
    count = FaultyDisk(tmp / "svc-count")
    with count.active():
        svc = PipelineService(tmp / "svc-store", tmp / "svc-count", _Steps(), min_free_bytes=0)
        while svc.run_once():
            pass
    tally = {
        "sites": len(count.calls),
        "stopped_said": 0,
        "refused_at_start": 0,
        "jobs_failed": 0,
        "jobs_done_after_space_returned": 0,
        "attempts_spent_on_full_disk": 0,
        "half_written": 0,
    }
    for n in range(1, len(count.calls) + 1):
        work, free = tmp / f"svc-{n}", {"b": 10 << 30}
        disk = FaultyDisk(work, fail_at=n, persistent=True)
        with disk.active():
            try:
                svc = PipelineService(
                    tmp / "svc-store", work, _Steps(), min_free_bytes=1 << 20, resume_margin_bytes=1 << 20, free_bytes=lambda _p: free["b"]
                )
            except (RuntimeError, OSError):
                tally["refused_at_start"] += 1
                continue
            for _ in range(10):
                svc.run_once()
            tally["stopped_said"] += svc.state.startswith("STOPPED: disk full")
        disk.fail_at, free["b"] = None, free["b"] + (100 << 20)
        with disk.active():
            for _ in range(10):
                svc.run_once()
        jobs = svc.jobs.jobs()
        tally["jobs_failed"] += sum(j.status == "failed" for j in jobs)
        tally["jobs_done_after_space_returned"] += sum(j.status == "done" for j in jobs)
        tally["attempts_spent_on_full_disk"] += sum(max(0, j.attempts - 1) for j in jobs)
        tally["half_written"] += len(list(work.rglob("*.tmp")))
    return tally


def kill_rig(tmp: Path, kills: int, rng: random.Random) -> dict:
    store = tmp / "kill-rig"
    committed: list[str] = []
    tally = {"kills": 0, "reported_committed": 0, "missing": 0, "verify_problems": 0, "recovered_to_quarantine": 0}
    argv = cadsplat(
        "rig",
        "watch",
        "--simulate",
        "--trigger",
        "can",
        "--rate",
        "8",
        "--store",
        str(store),
        "--views",
        "3",
        "--size",
        "96",
        "72",
        "--min-free-gb",
        "0",
    )
    for _ in range(kills):
        out, killed = run_until_killed(argv, rng.uniform(0.0, 1.5), ready=("reference", "committed"))
        tally["kills"] += killed
        committed += reported(out)
        try:
            counts = store_after_kill(store, committed)
            tally["recovered_to_quarantine"] += counts["recovered"]
        except AssertionError as e:
            tally["missing" if "reported committed" in str(e) else "verify_problems"] += 1
    tally["reported_committed"] = len(committed)
    return tally


def kill_service(tmp: Path, kills: int, rng: random.Random) -> dict:
    from reconstruction.library import build_library

    store, work, lib = tmp / "kill-svc-S", tmp / "kill-svc-W", tmp / "kill-svc-L"
    out, _ = run_until_killed(
        cadsplat(
            "rig",
            "watch",
            "--simulate",
            "--trigger",
            "can",
            "--rate",
            "4",
            "--max-captures",
            "2",
            "--store",
            str(store),
            "--views",
            "4",
            "--size",
            "128",
            "96",
            "--min-free-gb",
            "0",
        ),
        300,
    )
    build_library(REPO / "sample" / "library_meshes", lib, progress=False, log=lambda _m: None)
    argv = cadsplat(
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
        "2",
    )
    tally = {"captures": len(reported(out)), "kills": 0, "half_written_published": 0}
    for _ in range(kills):
        _, killed = run_until_killed(argv, rng.uniform(0.5, 8.0), ready=("resumed", "enqueued", "step-"))
        tally["kills"] += killed
        try:
            work_after_kill(work)
        except Exception:  # noqa: BLE001 - any unreadable published output counts
            tally["half_written_published"] += 1
    final, killed = run_until_killed(argv, 1200)
    statuses = job_statuses(work)
    after = work_after_kill(work)
    tally.update(
        {
            "jobs_done": statuses.count("done"),
            "jobs_failed": statuses.count("failed"),
            "twins_verifying": after["twins"],
            "exports": after["exports"],
            "leftovers_after_final_run": after["leftovers"],
        }
    )
    return tally


def _spill_one(spill_root: Path, store: Path) -> str:
    """One capture waiting in `store`'s spill (as a rig leaves it when the store stayed read-only); returns its id."""
    import numpy as np

    from calibration.camera import Camera
    from calibration.capture import FrameData
    from rig.store import Spill

    k = np.array([[80.0, 0, 48], [0, 80.0, 36], [0, 0, 1]])
    frames = [
        FrameData(f"cam{i}", np.full((72, 96, 3), 60 + 40 * i, np.uint8), Camera(k, 96, 72, np.zeros(0), np.eye(4)), f"cam{i}", i)
        for i in range(3)
    ]
    capture_id = "090000-20260101T000000Z"  # above any id the rig reaches here, so the import cannot collide
    Spill(spill_root, store).write(capture_id, frames, {"rig_id": "bench"})
    return capture_id


def two_writers(tmp: Path, runs: int) -> dict:
    """`rig watch` holds a store; a second `rig watch --max-captures 2`, then a `rig capture`, are started on it."""
    import subprocess

    from deploy.commands.store import verify_store
    from tests.deploy.test_rig_cli import SMALL, _env, watching

    tally = {
        "runs": runs,
        "second_writers": 0,
        "refused": 0,
        "named_first_pid": 0,
        "not_one_sentence": 0,
        "second_captures": 0,
        "first_captures": 0,
        "reused_ids": 0,
        "quarantined": 0,
        "verify_problems": 0,
    }
    for n in range(runs):
        store = tmp / f"writers-{n}"
        with watching(store) as first:
            for argv in (("watch", "--simulate", "--rate", "4", "--max-captures", "2"), ("capture", "--simulate")):
                r = subprocess.run(
                    cadsplat("rig", *argv, "--store", str(store), *SMALL),
                    capture_output=True,
                    text=True,
                    env=_env(),
                    cwd=REPO,
                    timeout=300,
                    check=False,
                )
                tally["second_writers"] += 1
                tally["refused"] += r.returncode != 0
                tally["named_first_pid"] += f"(pid {first.pid})" in r.stderr
                tally["not_one_sentence"] += not one_sentence(r.stderr.strip())
                tally["second_captures"] += len(reported(r.stdout))
        ids = reported(first.result[1])
        tally["first_captures"] += len(ids)
        tally["reused_ids"] += len(ids) - len(set(ids))
        tally["quarantined"] += sum(1 for _ in (store / "quarantine").iterdir())
        tally["verify_problems"] += len(verify_store(store, tmp / "no-spill")[1])
    return tally


def import_during_watch(tmp: Path, runs: int, per_run: int = 5) -> dict:
    """`store import-spill` started `per_run` times while `rig watch` writes (a capture waits in the spill); then once
    after the rig stopped."""
    import subprocess

    from deploy.commands.store import verify_store
    from tests.deploy.test_rig_cli import SMALL, _env, watching

    tally = {
        "runs": runs,
        "imports_during_watch": 0,
        "refused": 0,
        "named_rig_pid": 0,
        "not_one_sentence": 0,
        "quarantined": 0,
        "rig_captures": 0,
        "imported_after_stop": 0,
        "verify_problems": 0,
    }
    for n in range(runs):
        store, spill = tmp / f"import-{n}", tmp / f"import-{n}.spill"
        waiting = _spill_one(spill, store)
        argv = cadsplat("store", "import-spill", str(store), "--spill", str(spill))
        with watching(store, "--rate", "8", *SMALL) as rig:
            for _ in range(per_run):
                r = subprocess.run(argv, capture_output=True, text=True, env=_env(), cwd=REPO, timeout=300, check=False)
                tally["imports_during_watch"] += 1
                tally["refused"] += r.returncode != 0
                tally["named_rig_pid"] += f"(pid {rig.pid})" in r.stderr
                tally["not_one_sentence"] += r.returncode != 0 and not one_sentence(r.stderr.strip())
        tally["rig_captures"] += len(reported(rig.result[1]))
        tally["quarantined"] += sum(1 for _ in (store / "quarantine").iterdir())
        r = subprocess.run(argv, capture_output=True, text=True, env=_env(), cwd=REPO, timeout=300, check=False)
        tally["imported_after_stop"] += r.returncode == 0 and f"imported {waiting}" in r.stdout
        tally["verify_problems"] += len(verify_store(store, spill)[1])
    return tally


def verify_during_watch(tmp: Path, verifies: int, per_run: int = 20) -> dict:
    """`store verify` (in-process, as the CLI runs it) `verifies` times while `rig watch` writes 8 views of 640x480 at
    4 Hz, in runs of `per_run` (0.2 s apart) on a fresh store. `saw_live_write`: runs that found a capture in .incoming/ (each a
    false alarm before the writer's lock was asked)."""
    from deploy.commands.store import verify_store
    from tests.deploy.test_rig_cli import watching

    tally = {"verifies": 0, "saw_live_write": 0, "false_alarms": 0, "rig_captures": 0, "verify_problems_after_stop": 0}
    for n in range(-(-verifies // per_run)):
        store = tmp / f"verify-{n}"
        with watching(store, "--rate", "4", "--views", "8", "--size", "640", "480", "--min-free-gb", "0") as rig:
            for _ in range(min(per_run, verifies - tally["verifies"])):
                counts, problems = verify_store(store, tmp / "no-spill")
                tally["verifies"] += 1
                tally["saw_live_write"] += counts["in_flight"] > 0
                tally["false_alarms"] += bool(problems)
                time.sleep(0.2)
        tally["rig_captures"] += len(reported(rig.result[1]))
        tally["verify_problems_after_stop"] += len(verify_store(store, tmp / "no-spill")[1])
    return tally


BOMBS = ((12000, 12000), (30000, 30000))


def _peak_rss(argv: list[str], err_path: Path) -> tuple[int, float, str]:
    """Run `argv` to its end: (exit code, its peak RSS in MB from the kernel's rusage of that child, its stderr)."""
    with open(err_path, "w") as err:
        proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=err, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, usage.ru_maxrss / 1024, err_path.read_text().strip()


def bomb_capture(tmp: Path, width: int, height: int) -> tuple[Path, int]:
    """A 2-view capture whose second image is an all-black PNG declaring width x height, its manifest updated to match."""
    import json

    import numpy as np

    from calibration.camera import Camera
    from calibration.capture import FrameData, write_capture
    from calibration.fileio import sha256_file
    from tests.calibration.test_capture import png_bomb

    cam, rng = Camera.from_fov(1.0, 48, 36), np.random.default_rng(0)
    root = write_capture(
        tmp / f"bomb-{width}x{height}",
        [FrameData(f"v{i}", rng.integers(0, 255, (36, 48, 3), dtype=np.uint8), cam, f"cam{i}") for i in range(2)],
    ).root
    size = png_bomb(root / "images/v1.png", width, height)
    doc = json.loads((root / "transforms.json").read_text())
    doc["cadsplat"]["sha256"]["images/v1.png"] = sha256_file(root / "images/v1.png")
    (root / "transforms.json").write_text(json.dumps(doc))
    return root, size


def bomb_runs(tmp: Path) -> list[dict]:
    """Each bomb through `cadsplat register` (refused from its header), and the 12000x12000 one decoded as read_image did
    before the cap (cv2.imdecode, then float32), each in its own process."""
    from reconstruction.library import build_library

    lib = tmp / "bomb-lib"
    build_library(REPO / "sample" / "library_meshes", lib, progress=False, log=lambda _m: None)
    rows, caps = [], [bomb_capture(tmp, width, height) for width, height in BOMBS]
    for (width, height), (cap, size) in zip(BOMBS, caps):
        rc, peak, err = _peak_rss(cadsplat("register", str(cap), "--library", str(lib), "--out", str(tmp / "reg.json")), tmp / "bomb.err")
        rows.append(
            {
                "image": f"{width}x{height} RGB PNG, {size / 1024:.0f} KB",
                "run": "cadsplat register",
                "exit": rc,
                "refused_before_decoding": "not decoded" in err,
                "one_sentence": one_sentence(err),
                "peak_rss_mb": f"{peak:.0f}",
            }
        )
    cap, size = caps[0]
    decode = (
        "import sys, cv2, numpy as np; d = np.fromfile(sys.argv[1], np.uint8); "
        "img = cv2.imdecode(d, cv2.IMREAD_UNCHANGED); print(np.ascontiguousarray(img, dtype=np.float32).shape)"
    )
    rc, peak, _ = _peak_rss([sys.executable, "-c", decode, str(cap / "images/v1.png")], tmp / "decode.err")
    rows.append(
        {
            "image": f"{BOMBS[0][0]}x{BOMBS[0][1]} RGB PNG, {size / 1024:.0f} KB",
            "run": "decoded without the cap (read_image before)",
            "exit": rc,
            "refused_before_decoding": False,
            "one_sentence": "-",
            "peak_rss_mb": f"{peak:.0f}",
        }
    )
    return rows


def rows_table(title: str, rows: list[dict]) -> str:
    return (
        f"### {title}\n\n| "
        + " | ".join(rows[0])
        + " |\n|"
        + "---|" * len(rows[0])
        + "\n"
        + "".join("| " + " | ".join(str(v) for v in r.values()) + " |\n" for r in rows)
    )


# A service whose register step of capture 000000 dies as an OOM-killed process does: SIGKILL, no clean-up.
POISON_SERVICE = """
import os, signal, sys
from pathlib import Path
from deploy.service import PipelineService
def step(name, job, work_dir, previous):
    if job.capture_id.startswith("000000") and name == "register":
        os.kill(os.getpid(), signal.SIGKILL)
    return {"step": name}
svc = PipelineService(Path(sys.argv[1]), Path(sys.argv[2]), step, max_attempts=int(sys.argv[3]))
while svc.run_once():
    pass
"""


def poison_job(tmp: Path, max_attempts: int = 3, restart_limit: int = 20) -> dict:
    """Restart the service after every death (systemd's Restart=) until it exits by itself or `restart_limit`."""
    import subprocess
    import sys

    from deploy.jobs import JobStore
    from tests.deploy.test_service import make_captures

    store, work = tmp / "poison-S", tmp / "poison-W"
    make_captures(store, 3)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    deaths = 0
    for _ in range(restart_limit):
        rc = subprocess.run(
            [sys.executable, "-c", POISON_SERVICE, str(store), str(work), str(max_attempts)], check=False, env=env, timeout=300
        ).returncode
        if rc == 0:
            break
        deaths += 1
    jobs = JobStore(work / "jobs.sqlite").jobs()
    history = subprocess.run(
        cadsplat("service", "history", "--work", str(work)), capture_output=True, text=True, check=False, env=env, timeout=120
    ).stdout
    poison = jobs[0]
    return {
        "max_attempts": max_attempts,
        "service_deaths": deaths,
        "queue_drained": rc == 0,
        "poison_status": poison.status,
        "poison_error": f"`{poison.error}`",
        "in_history": bool(poison.error) and poison.error in history,
        "next_jobs_done": sum(j.status == "done" for j in jobs[1:]),
        "next_jobs": len(jobs) - 1,
    }


def table(title: str, tally: dict) -> str:
    return (
        f"### {title}\n\n| "
        + " | ".join(tally)
        + " |\n|"
        + "---|" * len(tally)
        + "\n| "
        + " | ".join(str(v) for v in tally.values())
        + " |\n"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kills", type=int, default=100, help="SIGKILLs of rig watch (acceptance: 100)")
    ap.add_argument(
        "--service-kills", type=int, default=None, help="SIGKILLs of service run (default: --kills; 0 skips part 3, the slowest)"
    )
    ap.add_argument(
        "--parts",
        default="sites,kills",
        help="comma-separated: sites (parts 1), kills (parts 2 and 3), "
        "two-writers, import-during-watch, verify-during-watch (part 4), bomb (part 5), poison (part 6)",
    )
    ap.add_argument("--writer-runs", type=int, default=10, help="runs of the two-writers and import-during-watch parts")
    ap.add_argument("--verifies", type=int, default=100, help="store verify runs of the verify-during-watch part (acceptance: 100)")
    ap.add_argument("--out", type=Path, default=RESULTS / "faults.md")
    ap.add_argument("--seed", type=int, default=16)
    args = ap.parse_args()
    rng = random.Random(args.seed)
    tmp = Path(tempfile.mkdtemp(prefix="bench-faults-"))
    sections, t0 = [], time.perf_counter()
    parts = set(args.parts.split(","))
    service_kills = args.kills if args.service_kills is None else args.service_kills
    try:
        if "sites" in parts:
            for mode in ("enospc", "filled", "erofs", "erofs-until-stop"):
                sections.append(
                    table(f"Rig store, {mode} at each write site (a reference + {TRIGGERS} captures per run)", rig_sweep(tmp, mode))
                )
                print(sections[-1], flush=True)
            sections.append(table("Calibration keeper, ENOSPC at each write site", keeper_sweep(tmp)))
            print(sections[-1], flush=True)
            sections.append(table("Service, ENOSPC from each write site on, then space returns", service_sweep(tmp)))
            print(sections[-1], flush=True)
        if "kills" in parts and args.kills:
            sections.append(table(f"SIGKILL of `rig watch --simulate` at {args.kills} random points", kill_rig(tmp, args.kills, rng)))
            print(sections[-1], flush=True)
        if "kills" in parts and service_kills:
            sections.append(
                table(
                    f"SIGKILL of `service run` at {service_kills} random points, then one run to the end",
                    kill_service(tmp, service_kills, rng),
                )
            )
            print(sections[-1], flush=True)
        if "two-writers" in parts:
            sections.append(
                table(
                    f"Two writers on one store: a second `rig watch` and a `rig capture` while `rig watch` runs ({args.writer_runs} runs)",
                    two_writers(tmp, args.writer_runs),
                )
            )
            print(sections[-1], flush=True)
        if "import-during-watch" in parts:
            sections.append(
                table(
                    f"`store import-spill` during `rig watch` ({args.writer_runs} runs of 5, a capture waiting in the spill)",
                    import_during_watch(tmp, args.writer_runs),
                )
            )
            print(sections[-1], flush=True)
        if "verify-during-watch" in parts:
            sections.append(table(f"`store verify` during `rig watch` ({args.verifies} verifies)", verify_during_watch(tmp, args.verifies)))
            print(sections[-1], flush=True)
        if "bomb" in parts:
            sections.append(rows_table("PNG decompression bombs in a capture (issue 58, 9)", bomb_runs(tmp)))
            print(sections[-1], flush=True)
        if "poison" in parts:
            sections.append(
                table("A poison job: its register step SIGKILLs the service, which is restarted after each death", poison_job(tmp))
            )
            print(sections[-1], flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    head = (
        f"# Fault injection (issue 16)\n\n`python -m benchmarks.bench_faults --parts {args.parts} --kills {args.kills} --service-kills {service_kills}`, "
        f"{time.perf_counter() - t0:.0f} s, "
        f"load average {os.getloadavg()[0]:.1f} at the end.\n\n"
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(head + "\n".join(sections))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np

from calibration.camera import Camera
from calibration.capture import FrameData, write_capture
from deploy.jobs import STEPS, JobStore
from deploy.service import PipelineService


def make_captures(store: Path, n: int) -> list[Path]:
    k = np.array([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]])
    paths = []
    for i in range(n):
        img = np.full((16, 16, 3), 100 + i, np.uint8)
        paths.append(
            write_capture(store / "captures" / f"{i:06d}-20261121T000000Z", [FrameData("cam0", img, Camera(k, 16, 16), "cam0")]).root
        )
    return paths


class CountingRunner:
    def __init__(self, fail: dict[str, int] | None = None):
        self.calls: list[tuple[str, str]] = []
        self.fail = dict(fail or {})

    def __call__(self, step, job, work_dir, previous):
        self.calls.append((job.capture_id, step))
        if self.fail.get(step, 0) > 0:
            self.fail[step] -= 1
            raise RuntimeError(f"{step} blew up")
        assert set(previous) == set(STEPS[: STEPS.index(step)])
        return {"step": step, "out": str(work_dir / step)}


def test_every_capture_becomes_one_job_and_steps_run_in_order(tmp_path):
    make_captures(tmp_path / "store", 3)
    runner = CountingRunner()
    svc = PipelineService(tmp_path / "store", tmp_path / "work", runner, max_queue=2)
    assert svc.scan() == 2  # bounded queue: the third waits in the store
    assert svc.run_forever(poll_s=0.01, max_jobs=3) == 3
    assert [c for c in runner.calls if c[0].startswith("000000")] == [("000000-20261121T000000Z", s) for s in STEPS]
    assert svc.jobs.count("done") == 3 and svc.scan() == 0


def test_failed_step_is_retried_then_reported_never_lost(tmp_path):
    make_captures(tmp_path / "store", 1)
    events = []
    runner = CountingRunner(fail={"reconstruct": 5})
    svc = PipelineService(tmp_path / "store", tmp_path / "work", runner, max_attempts=3, on_event=events.append)
    for _ in range(5):
        svc.run_once()
    job = svc.jobs.jobs()[0]
    assert job.status == "failed" and job.attempts == 3 and "reconstruct blew up" in job.error
    # register ran once: retries resume at the failed step.
    assert runner.calls.count((job.capture_id, "register")) == 1
    assert runner.calls.count((job.capture_id, "reconstruct")) == 3
    assert [e.kind for e in events].count("job-retry") == 2 and events[-1].kind == "job-failed"
    svc.jobs.retry(job.id)
    runner.fail.clear()
    svc.run_once()
    assert svc.jobs.get(job.id).status == "done"


CRASHY = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from deploy.service import PipelineService
    store, work, log = map(Path, sys.argv[1:4])
    def runner(step, job, work_dir, previous):
        with open(log, "a") as f:
            f.write(step + "\\n")
        if step == "reconstruct" and sys.argv[4] == "hang":
            time.sleep(600)
        return {"step": step}
    PipelineService(store, work, runner).run_forever(poll_s=0.05, max_jobs=1)
    """
)


def test_killed_mid_reconstruction_resumes_from_last_finished_step(tmp_path):
    store, work, log = tmp_path / "store", tmp_path / "work", tmp_path / "calls.log"
    make_captures(store, 1)
    before = sorted(p.name for p in (store / "captures").iterdir())
    script = tmp_path / "svc.py"
    script.write_text(CRASHY)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    proc = subprocess.Popen([sys.executable, str(script), str(store), str(work), str(log), "hang"], env=env)
    deadline = time.time() + 60
    while time.time() < deadline and "reconstruct" not in (log.read_text() if log.exists() else ""):
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert log.read_text().split() == ["register", "reconstruct"]
    # Restart: the interrupted step is redone, the finished one is not.
    subprocess.run([sys.executable, str(script), str(store), str(work), str(log), "ok"], env=env, check=True, timeout=60)
    assert log.read_text().split() == ["register", "reconstruct", "reconstruct", "export"]
    jobs = JobStore(work / "jobs.sqlite")
    assert [j.status for j in jobs.jobs()] == ["done"]
    assert sorted(p.name for p in (store / "captures").iterdir()) == before


def test_stopping_mid_step_requeues_without_spending_an_attempt(tmp_path):
    from deploy.service import StepInterrupted

    make_captures(tmp_path / "store", 1)

    def runner(step, job, work_dir, previous):
        if step == "reconstruct":
            raise StepInterrupted(step)
        return {}

    svc = PipelineService(tmp_path / "store", tmp_path / "work", runner)
    svc.run_once()
    job = svc.jobs.jobs()[0]
    assert job.status == "queued" and job.attempts == 0 and job.error == ""
    assert job.steps["register"]["status"] == "done" and job.steps["reconstruct"]["status"] == "pending"


@__import__("pytest").mark.slow
def test_readme_flow_rig_watch_then_service_run_makes_a_twin_of_every_capture(tmp_path, monkeypatch, capsys):
    """Issue 16 (1): `rig watch --simulate --trigger can --max-captures 2 --store S` then `service run --store S
    --work W --library L` used to fail every job with "has neither masks/ nor background/ frames"."""
    from dataclasses import replace

    from deploy.cli import main
    from reconstruction import presets
    from reconstruction.library import build_library
    from tests.conftest import REPO
    from tests.rig.conftest import assert_store_sound

    store, work, lib = tmp_path / "S", tmp_path / "W", tmp_path / "L"
    r = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys; from deploy.cli import main; sys.exit(main())",
            "rig",
            "watch",
            "--simulate",
            "--trigger",
            "can",
            "--rate",
            "3",
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
        ],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        cwd=REPO,
        timeout=180,
    )
    assert r.returncode == 0, r.stderr
    ids = [line.split()[1] for line in r.stdout.splitlines() if line.startswith("committed ")]
    assert len(ids) == 2 and assert_store_sound(store, ids) == sorted(ids)
    assert r.stdout.startswith("reference reference-v0001: empty-rig frames taken")
    build_library(REPO / "sample" / "library_meshes", lib, progress=False, log=lambda _m: None)
    original = presets.resolve_preset
    monkeypatch.setattr(
        "reconstruction.presets.resolve_preset",
        lambda name, stats: replace(original(name, stats), iters_pose=20, iters_deform=10, iters_photo=20, dropout_anneal=10),
    )
    capsys.readouterr()
    assert (
        main(
            [
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
                "--max-jobs",
                "2",
                "--poll",
                "0.1",
                "--min-free-gb",
                "0",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert out.count("job-done") == 2 and "job-failed" not in out and "job-retry" not in out, out
    jobs = JobStore(work / "jobs.sqlite").jobs()
    assert [j.status for j in jobs] == ["done", "done"]
    for j in jobs:
        twin = Path(j.steps["reconstruct"]["output"]["twin"])
        assert (twin / "manifest.json").exists() and (twin / "twin.json").exists()
        assert json_meta(store, j.capture_id)["background_id"] == "reference-v0001"


def json_meta(store: Path, capture_id: str) -> dict:
    import json

    return json.loads((store / "captures" / capture_id / "transforms.json").read_text())["cadsplat"]


def test_read_only_work_dir_is_one_sentence(tmp_path, capsys):
    """Issue 16 (6): `service run` with a read-only work dir printed a sqlite3 traceback. A tmpfs remounted
    read-only (file modes do not stop root); skipped where mounting is not allowed."""
    import pytest

    from deploy.cli import main

    mnt = tmp_path / "ro"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt)], capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here (needs root / CAP_SYS_ADMIN)")
    try:
        (mnt / "W").mkdir()
        subprocess.run(["mount", "-o", "remount,ro", str(mnt)], check=True, capture_output=True)
        rc = main(
            ["service", "run", "--store", str(tmp_path / "S"), "--work", str(mnt / "W"), "--library", str(tmp_path), "--max-jobs", "1"]
        )
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)
    err = capsys.readouterr().err.strip()
    assert rc != 0 and err.startswith("Error: cannot open the job store") and len(err.splitlines()) == 1, err


def test_garbage_job_store_is_one_sentence(tmp_path, capsys):
    from deploy.cli import main

    work = tmp_path / "W"
    work.mkdir()
    (work / "jobs.sqlite").write_bytes(b"this is not a database" * 100)
    rc = main(["service", "run", "--store", str(tmp_path / "S"), "--work", str(work), "--library", str(tmp_path), "--max-jobs", "1"])
    err = capsys.readouterr().err.strip()
    assert rc != 0 and err.startswith("Error: cannot open the job store") and "not a database" in err and len(err.splitlines()) == 1


def test_full_disk_stops_the_service_without_failing_a_job_and_resumes(tmp_path):
    make_captures(tmp_path / "store", 2)
    free = {"b": 10 << 20}
    events = []
    svc = PipelineService(
        tmp_path / "store",
        tmp_path / "work",
        CountingRunner(),
        min_free_bytes=50 << 20,
        resume_margin_bytes=1 << 20,
        free_bytes=lambda _p: free["b"],
        on_event=events.append,
    )
    assert not svc.run_once() and not svc.run_once()
    assert svc.state.startswith("STOPPED: disk full") and [e.kind for e in events] == ["stopped"]
    free["b"] = 100 << 20
    while svc.run_once():
        pass
    assert svc.state == "" and [j.status for j in svc.jobs.jobs()] == ["done", "done"]
    assert [e.kind for e in events][:2] == ["stopped", "resumed"]


HOLDS = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from deploy.service import PipelineService
    store, work, log = map(Path, sys.argv[1:4])
    def runner(step, job, work_dir, previous):
        log.write_text(step)
        time.sleep(600)
    PipelineService(store, work, runner).run_forever(poll_s=0.05, max_jobs=1)
    """
)


def test_a_second_service_on_one_work_dir_is_refused_and_leaves_the_running_job_alone(tmp_path):
    """Issue 58 (7): a second `service run` on the same --work put the first one's running job back in the queue."""
    store, work, log = tmp_path / "store", tmp_path / "work", tmp_path / "started"
    make_captures(store, 1)
    script = tmp_path / "svc.py"
    script.write_text(HOLDS)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    first = subprocess.Popen([sys.executable, str(script), str(store), str(work), str(log)], env=env)
    try:
        deadline = time.time() + 60
        while time.time() < deadline and not log.exists():
            time.sleep(0.05)
        assert log.read_text() == "register"
        for argv in (
            ["service", "status", "--work", str(work)],
            ["service", "run", "--store", str(store), "--work", str(work), "--library", str(tmp_path), "--max-jobs", "1"],
        ):
            r = subprocess.run(
                [sys.executable, "-m", "deploy.cli", *argv], env=env, capture_output=True, text=True, check=False, timeout=120
            )
            if argv[1] == "run":
                assert r.returncode != 0 and len(r.stderr.strip().splitlines()) == 1, r.stderr
                assert f"pid {first.pid}" in r.stderr and "Traceback" not in r.stderr
        job = JobStore(work / "jobs.sqlite").jobs()[0]
        assert job.status == "running" and job.steps["register"]["status"] == "running"
    finally:
        first.kill()
        first.wait()


POISON = textwrap.dedent(
    """
    import os, sys
    from pathlib import Path
    from deploy.service import PipelineService
    store, work = map(Path, sys.argv[1:3])
    def runner(step, job, work_dir, previous):
        if job.capture_id.startswith("000000") and step == "register":
            os._exit(137)  # as an OOM kill or a native crash ends the service: no exception, no clean-up
        return {"step": step}
    PipelineService(store, work, runner, max_attempts=3).run_forever(poll_s=0.05, max_jobs=1)
    """
)


def test_a_job_that_kills_the_service_is_given_up_after_max_attempts_and_the_next_is_done(tmp_path, capsys):
    """Issue 58 (8): a job whose step killed the service was requeued on every restart, uncounted, and claimed first."""
    from deploy.cli import main

    store, work = tmp_path / "store", tmp_path / "work"
    make_captures(store, 2)
    script = tmp_path / "svc.py"
    script.write_text(POISON)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    codes = [
        subprocess.run([sys.executable, str(script), str(store), str(work)], check=False, env=env, timeout=120).returncode for _ in range(4)
    ]
    assert codes == [137, 137, 137, 0]  # as under systemd's Restart=: three deaths, then the queue moves on
    poison, nxt = JobStore(work / "jobs.sqlite").jobs()
    assert poison.status == "failed" and poison.attempts == 3
    assert poison.error == "register: the service died during register (attempt 3 of 3); given up"
    assert nxt.status == "done"
    assert main(["service", "history", "--work", str(work)]) == 0
    assert f"job {poison.id:<4} {poison.capture_id:<28} FAILED {poison.error}" in capsys.readouterr().out

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
        paths.append(write_capture(store / "captures" / f"{i:06d}-20261121T000000Z", [FrameData("cam0", img, Camera(k, 16, 16), "cam0")]).root)
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

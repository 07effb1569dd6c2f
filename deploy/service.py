"""The pipeline service: committed captures -> registered -> reconstructed -> exported twins.

It watches a capture store (`captures/<id>/`), enqueues each new capture once in the job store,
and runs every job's remaining steps in order. Work is bounded: at most `max_queue` jobs wait at
once; further captures stay safely in the store and are enqueued as the queue drains. A capture
is never moved or deleted by the service, so a crash can lose no capture; a restart resumes each
job at its first unfinished step.

A full disk is not a job's failure: the step in flight goes back to pending without spending an
attempt, the service says "STOPPED: disk full" (`state`, and a "stopped" event) and claims no job
until space returns, then says "resumed" and carries on where it stopped.
"""

from __future__ import annotations

import shutil
import signal
import sqlite3
import threading
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

from calibration.guard import ProcessLock, hold_lock
from deploy.jobs import STEPS, Job, JobStore, JobStoreError, is_disk_full

# This process's hold on each work directory it serves (one service per work directory across processes;
# a process may open its own again, as a restart in one process does).
_WORK_LOCKS: dict[Path, ProcessLock] = {}


class StepInterrupted(Exception):
    """Raised from inside a step (e.g. by its progress callback) when the service is stopping."""


class StepRunner(Protocol):
    """Runs one step of one job and returns what it produced (JSON-able); raises on failure."""

    def __call__(self, step: str, job: Job, work_dir: Path, previous: dict[str, dict]) -> dict: ...


@dataclass
class ServiceEvent:
    kind: str  # "enqueued", "step-started", "step-done", "job-done", "job-failed", "job-retry", "stopped", "resumed"
    job_id: int
    capture_id: str
    step: str = ""
    detail: dict = field(default_factory=dict)


class PipelineService:
    """`store_root`: the rig's capture store; `work_root`: where jobs write (job store, twins).

    One service per work directory: a second process is refused (`LockHeld`, naming the holder's pid)
    before it opens the job store, so it never requeues the first one's running job.
    """

    def __init__(
        self,
        store_root: str | Path,
        work_root: str | Path,
        run_step: StepRunner,
        *,
        max_queue: int = 8,
        max_attempts: int = 3,
        on_event: Callable[[ServiceEvent], None] | None = None,
        min_free_bytes: int = 256 << 20,
        resume_margin_bytes: int = 64 << 20,
        free_bytes: Callable[[Path], int] = lambda p: shutil.disk_usage(p).free,
    ) -> None:
        self.captures_dir = Path(store_root) / "captures"
        self.work_root = Path(work_root)
        self.work_root.mkdir(parents=True, exist_ok=True)
        hold_work_dir(self.work_root)
        self.on_event = on_event or (lambda e: None)
        self.jobs = JobStore(self.work_root / "jobs.sqlite", max_attempts=max_attempts)
        # The jobs whose step this directory's last service died in: requeued, or given up after max_attempts.
        self.recovered = self.jobs.recover()
        for job in self.recovered:
            if job.status == "failed":
                self.on_event(ServiceEvent("job-failed", job.id, job.capture_id, job.current_step, {"error": job.error}))
        self.run_step = run_step
        self.max_queue = max_queue
        self.min_free_bytes, self.resume_margin_bytes, self._free_bytes = int(min_free_bytes), int(resume_margin_bytes), free_bytes
        self.state = ""  # "" while serving, else "STOPPED: disk full ..."
        self._full_at: int | None = None
        self._stop = threading.Event()

    # ---- disk ----------------------------------------------------------------------------------

    def _disk_full(self, why: str) -> None:
        free = int(self._free_bytes(self.work_root))
        self._full_at = free if self._full_at is None else min(self._full_at, free)
        first = not self.state
        self.state = f"STOPPED: disk full ({why}; {free / 1e6:.0f} MB free under {self.work_root}); jobs resume when space is freed"
        if first:
            self.on_event(ServiceEvent("stopped", 0, "", detail={"error": self.state}))

    def room(self) -> bool:
        """True when there is room to run a job; False (and `state` says why) while the disk is full."""
        free = int(self._free_bytes(self.work_root))
        if free < self.min_free_bytes:
            self._disk_full(f"below the {self.min_free_bytes / 1e6:.0f} MB threshold")
            return False
        if self._full_at is not None and free < self._full_at + self.resume_margin_bytes:
            return False
        if self.state:
            self.state, self._full_at = "", None
            self.jobs.requeue_interrupted(refund=True)
            self.on_event(ServiceEvent("resumed", 0, "", detail={"free_bytes": free}))
        return True

    def job_dir(self, job: Job) -> Path:
        return self.work_root / "jobs" / job.capture_id

    def scan(self) -> int:
        """Enqueue new committed captures, oldest first, while the queue has room. Returns how many."""
        if not self.captures_dir.exists():
            return 0
        room = self.max_queue - self.jobs.count("queued")
        added = 0
        for cap in sorted(p for p in self.captures_dir.iterdir() if (p / "transforms.json").exists()):
            if room <= 0:
                break
            if self.jobs.add(cap.name, cap):
                job = next(j for j in self.jobs.jobs("queued") if j.capture_id == cap.name)
                self.on_event(ServiceEvent("enqueued", job.id, job.capture_id))
                room -= 1
                added += 1
        return added

    def run_job(self, job: Job) -> str:
        """Run `job`'s unfinished steps; returns the job's status afterwards."""
        work = self.job_dir(job)
        work.mkdir(parents=True, exist_ok=True)
        remove_half_written(work)
        for step in STEPS:
            if job.steps[step]["status"] == "done":
                continue
            previous = {s: job.steps[s]["output"] for s in STEPS if job.steps[s]["status"] == "done"}
            self.jobs.start_step(job.id, step)
            self.on_event(ServiceEvent("step-started", job.id, job.capture_id, step))
            try:
                output = self.run_step(step, job, work, previous)
            except StepInterrupted:
                self.jobs.interrupt(job.id, step)
                return "queued"
            except Exception as e:  # a failed step is recorded, retried, then reported: never lost
                if _caused_by_full_disk(e):
                    self.jobs.interrupt(job.id, step)  # not the job's fault: no attempt spent
                    self._disk_full(f"while {step} of {job.capture_id} was writing")
                    return "queued"
                msg = str(e).splitlines()[0] if str(e) else type(e).__name__
                status = self.jobs.fail_attempt(job.id, step, msg)
                kind = "job-failed" if status == "failed" else "job-retry"
                self.on_event(ServiceEvent(kind, job.id, job.capture_id, step, {"error": msg, "trace": traceback.format_exc(limit=3)}))
                return status
            self.jobs.finish_step(job.id, step, output)
            job = self.jobs.get(job.id)
            self.on_event(ServiceEvent("step-done", job.id, job.capture_id, step, output))
        self.jobs.finish_job(job.id)
        self.on_event(ServiceEvent("job-done", job.id, job.capture_id))
        return "done"

    def run_once(self) -> bool:
        """Scan, then run one queued job; False when there was nothing to do (or the disk is full)."""
        try:
            if not self.room():
                return False
            self.scan()
            job = self.jobs.claim_next()
            if job is None:
                return False
            self.run_job(job)
        except (sqlite3.OperationalError, OSError) as e:
            if not is_disk_full(e):
                raise
            # The job in flight stays "running" in the job store; it is requeued, its attempt refunded, on resuming.
            self._disk_full("the job store or a job's folder could not be written")
            return False
        return self.state == ""

    def run_forever(self, poll_s: float = 1.0, max_jobs: int | None = None) -> int:
        """Serve until stopped (SIGTERM/SIGINT finish the step in flight first) or `max_jobs` ran."""
        done = 0
        for sig in (signal.SIGTERM, signal.SIGINT):
            if threading.current_thread() is threading.main_thread():
                signal.signal(sig, lambda *_: self._stop.set())
        while not self._stop.is_set():
            if self.run_once():
                done += 1
                if max_jobs is not None and done >= max_jobs:
                    break
            else:
                self._stop.wait(poll_s)
        return done

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def stop(self) -> None:
        self._stop.set()


def hold_work_dir(work_root: Path) -> None:
    """Lock `work_root` for this process's life; raises LockHeld naming the other service's pid, JobStoreError
    where the lock cannot be written."""
    key = work_root.resolve()
    if key not in _WORK_LOCKS:
        try:
            _WORK_LOCKS[key] = hold_lock(key, "cadsplat service", name=".service.lock")
        except OSError as e:  # a read-only or full work directory: the job store beside the lock cannot be written either
            why = "the disk is full" if is_disk_full(e) else e.strerror or str(e)
            raise JobStoreError(f"cannot open the job store {key / 'jobs.sqlite'}: {why}") from None


def remove_half_written(folder: Path) -> list[Path]:
    """Delete what a killed write left under `folder`: hidden `.X.*.incoming` directories (a twin or an
    export being assembled) and `.X.*.tmp` files (an atomic write's temp file). Published outputs and
    the training checkpoint are kept. Returns what was removed."""
    gone = []
    for p in sorted(folder.rglob(".*"), key=lambda q: -len(q.parts)):
        if p.name.endswith(".incoming") and p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
            gone.append(p)
        elif p.name.endswith(".tmp") and p.is_file():
            p.unlink(missing_ok=True)
            gone.append(p)
    return gone


def _caused_by_full_disk(exc: BaseException) -> bool:
    """ENOSPC anywhere in the exception's chain (steps wrap I/O errors in their own sentences)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if is_disk_full(exc):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False

"""The job store: one SQLite file recording every capture's way to a twin, step by step.

A job is one capture. Its steps run in order; each finished step's outputs are recorded, so after
a crash or power loss the service resumes at the first unfinished step and never redoes a finished
one. A step found "running" at start-up was interrupted: it goes back to "pending" (its outputs
are written atomically, so nothing half-done is trusted). SQLite in WAL mode with synchronous=FULL
makes every state change durable before the call returns.

A job's `attempts` counts the starts of the step it is on, spent when the step starts: a step that
kills the service (an OOM kill, a native crash) has spent its attempt before it dies, so after
`max_attempts` such deaths the job is given up with why, and the queue moves on.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

STEPS: tuple[str, ...] = ("register", "reconstruct", "export")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    capture_id TEXT NOT NULL UNIQUE,
    capture_path TEXT NOT NULL,
    status TEXT NOT NULL DEFAULT 'queued',
    attempts INTEGER NOT NULL DEFAULT 0,
    error TEXT NOT NULL DEFAULT '',
    created REAL NOT NULL,
    updated REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS steps (
    job_id INTEGER NOT NULL REFERENCES jobs(id),
    step TEXT NOT NULL,
    status TEXT NOT NULL DEFAULT 'pending',
    started REAL,
    finished REAL,
    output TEXT NOT NULL DEFAULT '{}',
    PRIMARY KEY (job_id, step)
);
"""


class JobStoreError(RuntimeError):
    """The job store cannot be opened or written (read-only, full or damaged file); one plain sentence."""


def is_disk_full(exc: BaseException) -> bool:
    """ENOSPC from a file write, or SQLite's "database or disk is full"."""
    if isinstance(exc, sqlite3.OperationalError):
        return "full" in str(exc)
    if isinstance(exc, OSError):
        import errno

        return exc.errno in (errno.ENOSPC, errno.EDQUOT)
    return False


@dataclass(frozen=True)
class Job:
    id: int
    capture_id: str
    capture_path: str
    status: str
    attempts: int
    error: str
    steps: dict[str, dict]

    @property
    def next_step(self) -> str | None:
        return next((s for s in STEPS if self.steps[s]["status"] != "done"), None)

    @property
    def current_step(self) -> str:
        """The step in progress (or the last one, when the job has ended)."""
        return self.next_step or STEPS[-1]


class JobStore:
    """Jobs and their steps in `path` (SQLite). Safe to reopen after any crash.

    Opening only reads and records: the one service that owns the work directory recovers what a
    crash interrupted (`requeue_interrupted`), so `service status` beside a running service changes nothing.
    """

    def __init__(self, path: str | Path, *, max_attempts: int = 3) -> None:
        self.path = Path(path)
        self.max_attempts = max_attempts
        self._lock = threading.RLock()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            # One connection shared by the service and the kiosk's threads, serialised by a lock.
            self._db = sqlite3.connect(self.path, timeout=30.0, isolation_level=None, check_same_thread=False)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.executescript(_SCHEMA)
        except (sqlite3.Error, OSError) as e:
            raise self._cannot_open(e) from None

    def _cannot_open(self, e: BaseException) -> JobStoreError:
        why = "the disk is full" if is_disk_full(e) else getattr(e, "strerror", None) or str(e)
        return JobStoreError(f"cannot open the job store {self.path}: {why}")

    def close(self) -> None:
        self._db.close()

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                yield self._db
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    def _query(self, sql: str, args: tuple = ()) -> list[tuple]:
        with self._lock:
            return self._db.execute(sql, args).fetchall()

    def recover(self) -> list[Job]:
        """At a service's start: each step the service before it died in goes back to pending, its attempt
        spent; a job whose step has had `max_attempts` is given up, saying so. Returns those jobs."""
        try:
            with self._tx() as db:
                died = db.execute(
                    "SELECT s.job_id, s.step, j.attempts FROM steps s JOIN jobs j ON j.id = s.job_id WHERE s.status='running'"
                ).fetchall()
                now = time.time()
                for job_id, step, attempts in died:
                    given_up = attempts >= self.max_attempts
                    why = f"{step}: the service died during {step} (attempt {attempts} of {self.max_attempts})" + (
                        "; given up" if given_up else ""
                    )
                    db.execute("UPDATE steps SET status='pending', started=NULL WHERE job_id=? AND step=?", (job_id, step))
                    db.execute(
                        "UPDATE jobs SET status=?, error=?, updated=? WHERE id=?", ("failed" if given_up else "queued", why, now, job_id)
                    )
                db.execute("UPDATE jobs SET status='queued', updated=? WHERE status='running'", (now,))
            return [self.get(job_id) for job_id, _, _ in died]
        except (sqlite3.Error, OSError) as e:
            raise self._cannot_open(e) from None

    def requeue_interrupted(self, *, refund: bool = False) -> int:
        """Interrupted steps go back to pending; their jobs back to queued (`refund`: the attempt they
        were on is given back, when the interruption was the disk's fault, not the job's). Returns how many."""
        with self._tx() as db:
            n = db.execute("UPDATE steps SET status='pending', started=NULL WHERE status='running'").rowcount
            attempts = "MAX(attempts-1, 0)" if refund else "attempts"
            db.execute(f"UPDATE jobs SET status='queued', attempts={attempts}, updated=? WHERE status='running'", (time.time(),))
        return n

    def add(self, capture_id: str, capture_path: str | Path) -> bool:
        """Enqueue a capture once; returns False when it already has a job."""
        now = time.time()
        with self._tx() as db:
            cur = db.execute(
                "INSERT OR IGNORE INTO jobs (capture_id, capture_path, created, updated) VALUES (?, ?, ?, ?)",
                (capture_id, str(capture_path), now, now),
            )
            if cur.rowcount == 0:
                return False
            db.executemany("INSERT INTO steps (job_id, step) VALUES (?, ?)", [(cur.lastrowid, s) for s in STEPS])
        return True

    def count(self, status: str | None = None) -> int:
        if status is None:
            return self._query("SELECT COUNT(*) FROM jobs")[0][0]
        return self._query("SELECT COUNT(*) FROM jobs WHERE status=?", (status,))[0][0]

    def get(self, job_id: int) -> Job:
        rows = self._query("SELECT id, capture_id, capture_path, status, attempts, error FROM jobs WHERE id=?", (job_id,))
        if not rows:
            raise KeyError(f"no job {job_id}")
        row = rows[0]
        steps = {
            s: {"status": st, "started": a, "finished": b, "output": json.loads(o)}
            for s, st, a, b, o in self._query("SELECT step, status, started, finished, output FROM steps WHERE job_id=?", (job_id,))
        }
        return Job(row[0], row[1], row[2], row[3], row[4], row[5], steps)

    def jobs(self, status: str | None = None) -> list[Job]:
        q = "SELECT id FROM jobs" + (" WHERE status=?" if status else "") + " ORDER BY id"
        return [self.get(r[0]) for r in self._query(q, (status,) if status else ())]

    def claim_next(self) -> Job | None:
        """The oldest queued job, marked running, or None (its step's attempt is spent when the step starts)."""
        with self._tx() as db:
            row = db.execute("SELECT id FROM jobs WHERE status='queued' ORDER BY id LIMIT 1").fetchone()
            if row is None:
                return None
            db.execute("UPDATE jobs SET status='running', updated=? WHERE id=?", (time.time(), row[0]))
        return self.get(row[0])

    def start_step(self, job_id: int, step: str) -> None:
        """`step` is running: one attempt spent, before it can crash the process."""
        with self._tx() as db:
            db.execute("UPDATE steps SET status='running', started=? WHERE job_id=? AND step=?", (time.time(), job_id, step))
            db.execute("UPDATE jobs SET attempts=attempts+1, updated=? WHERE id=?", (time.time(), job_id))

    def finish_step(self, job_id: int, step: str, output: dict) -> None:
        with self._tx() as db:
            db.execute(
                "UPDATE steps SET status='done', finished=?, output=? WHERE job_id=? AND step=?",
                (time.time(), json.dumps(output), job_id, step),
            )
            db.execute("UPDATE jobs SET attempts=0, error='', updated=? WHERE id=?", (time.time(), job_id))  # the next step starts afresh

    def finish_job(self, job_id: int) -> None:
        with self._tx() as db:
            db.execute("UPDATE jobs SET status='done', error='', updated=? WHERE id=?", (time.time(), job_id))

    def fail_attempt(self, job_id: int, step: str, error: str) -> str:
        """Record a failed step: the job is retried until `max_attempts`, then failed. Returns the new status."""
        with self._tx() as db:
            attempts = db.execute("SELECT attempts FROM jobs WHERE id=?", (job_id,)).fetchone()[0]
            status = "failed" if attempts >= self.max_attempts else "queued"
            db.execute("UPDATE steps SET status='pending', started=NULL WHERE job_id=? AND step=?", (job_id, step))
            db.execute("UPDATE jobs SET status=?, error=?, updated=? WHERE id=?", (status, f"{step}: {error}", time.time(), job_id))
        return status

    def interrupt(self, job_id: int, step: str) -> None:
        """The service stopped mid-step (shutdown, not a failure): the step and job go back, no attempt counted."""
        with self._tx() as db:
            db.execute("UPDATE steps SET status='pending', started=NULL WHERE job_id=? AND step=?", (job_id, step))
            db.execute("UPDATE jobs SET status='queued', attempts=MAX(attempts-1, 0), updated=? WHERE id=?", (time.time(), job_id))

    def retry(self, job_id: int) -> None:
        """Operator re-run: a failed or finished job goes back to the queue with fresh attempts."""
        with self._tx() as db:
            db.execute("UPDATE jobs SET status='queued', attempts=0, error='', updated=? WHERE id=?", (time.time(), job_id))

"""The capture store: complete, verified captures or a quarantined entry with its reason; nothing else.

Layout under the store root:

    captures/<id>/       complete captures (calibration.capture format, sha256 of every file)
    quarantine/<id>/     incomplete or invalid captures, each with `reason.json`
    .incoming/           captures being written; never read by anyone else
    references/          the empty-rig reference, versioned (rig.reference)
    store.json           the capture counter (ids are never reused, even across crashes)
    .reserve             disk space held back for the next capture (released when the disk fills)
    .lock                the one writer's lock (`lock_store`): a rig or an import holds it for its life

A capture is assembled under `.incoming/<id>` by `calibration.capture.write_capture` (every file
fsynced, read back and verified), then renamed into `captures/` and both directories fsynced. A
crash at any point leaves either nothing under `captures/` or the complete capture; whatever is
left in `.incoming/` is moved to `quarantine/` with a reason the next time the store opens.

A full disk loses no capture: before a capture's frames are taken, `room_for` makes sure the disk
is above its threshold and holds `.reserve`, a file as large as the capture. When a write then
meets ENOSPC (another process filled the disk), the reserve is released and the write retried, so
the capture in flight is committed whole; the store says "STOPPED: disk full" and refuses further
captures (before their frames are taken) until space returns and the reserve can be held again.

A store that cannot be written at all (read-only, I/O error) loses no capture either: the rig
writes a capture it could not commit into the spill (`Spill`, a directory on another filesystem,
in this same capture format) and `CaptureStore.import_spill` moves it into the store under its id
once the store is writable again (the rig's next start, or `cadsplat store import-spill`).

One writer per store: opening a `CaptureStore` moves whatever is in `.incoming/` to quarantine and
continues the id counter, which is only sound when no other process writes. So every writer (the rig's
commands, `store import-spill`) takes `lock_store` before it opens the store, and a second one is
refused naming the first; a reader (`store verify`) asks `writer_holds` whether what is in
`.incoming/` is in flight rather than left by a crash.
"""

from __future__ import annotations

import datetime as dt
import errno
import hashlib
import json
import os
import re
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from calibration.capture import Capture, CaptureError, FrameData, read_capture, write_capture
from calibration.fileio import atomic_write_bytes, atomic_write_json, fsync_dir
from calibration.guard import LockHeld, ProcessLock, hold_lock
from rig.reference import ReferenceStore

CAPTURES, QUARANTINE, INCOMING, STATE = "captures", "quarantine", ".incoming", "store.json"
REFERENCES, RESERVE, LOCK = "references", ".reserve", ".lock"
REASON = "reason.json"
IMPORTING = ".import"  # suffix of a spilled capture being copied into .incoming/ (its source stays in the spill)
DISK_FULL = "STOPPED: disk full"
_ID = re.compile(r"^(\d{6,})-\d{8}T\d{6}Z")


class StoreError(RuntimeError):
    """The store cannot take a capture (disk full, unwritable); one plain sentence."""


@dataclass(frozen=True)
class StoredCapture:
    """Where a capture ended up: `status` is "committed" or "quarantined" (then `reason` says why)."""

    capture_id: str
    path: Path
    status: str
    reason: str = ""


def disk_free_bytes(path: Path) -> int:
    return shutil.disk_usage(path).free


def is_enospc(exc: BaseException) -> bool:
    return isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT)


def _allocate(path: Path, size: int) -> None:
    """A file of `size` bytes whose blocks are really allocated (ENOSPC now, not at a later write)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        try:
            os.posix_fallocate(fd, 0, size)
        except OSError as e:
            if e.errno not in (errno.EOPNOTSUPP, errno.EINVAL):
                raise
            block = b"\0" * (1 << 20)
            for off in range(0, size, len(block)):
                os.write(fd, block[: min(len(block), size - off)])
        os.fsync(fd)
    finally:
        os.close(fd)


def lock_store(root: str | os.PathLike, role: str) -> ProcessLock:
    """Make this process the store's one writer until it ends (or releases the lock); take it before opening the
    store. Raises calibration.guard.LockHeld, one sentence naming the writer that holds it and its pid."""
    return hold_lock(root, role, name=LOCK)


def writer_holds(root: str | os.PathLike) -> bool:
    """True while a writer holds the store's lock, so what its `.incoming/` holds is being written, not damage.

    Probes with a shared lock held for an instant; False when the store was never locked or its lock file cannot
    be opened (a read-only mount), so leftovers are then reported."""
    if not (Path(root) / LOCK).is_file():
        return False
    try:
        hold_lock(root, "store verify", name=LOCK, shared=True).release()
    except LockHeld:
        return True
    except OSError:
        return False
    return False


class CaptureStore:
    """A directory of captures that never holds a half-written one and never reuses an id.

    `min_free_bytes`: below this much free disk, `disk_ok()` is False and acquisition stops taking
    captures (stored ones are untouched). `free_bytes` is injectable for tests.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        *,
        min_free_bytes: int = 1 << 30,
        free_bytes: Callable[[Path], int] = disk_free_bytes,
    ) -> None:
        self.root = Path(root)
        self.min_free_bytes = int(min_free_bytes)
        self._free_bytes = free_bytes
        for sub in (CAPTURES, QUARANTINE, INCOMING):
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        self.alarm = ""
        self.references = ReferenceStore(self.root / REFERENCES)
        self.references.clean()
        self._next = self._load_counter()
        self.recovered: list[StoredCapture] = self._recover_incoming()

    # ---- ids ---------------------------------------------------------------------------------

    def _load_counter(self) -> int:
        """Next counter: the persisted one, but never below any id already on disk (state file lost or stale)."""
        persisted = 0
        try:
            persisted = int(json.loads((self.root / STATE).read_text())["next_counter"])
        except (FileNotFoundError, ValueError, KeyError, TypeError):
            pass
        seen = [
            int(m.group(1))
            for sub in (CAPTURES, QUARANTINE, INCOMING)
            for p in (self.root / sub).iterdir()
            if (m := _ID.match(p.name.lstrip(".")))
        ]
        return max([persisted, *(n + 1 for n in seen)])

    def reserve_id(self) -> str:
        """A new capture id: the counter is persisted (atomically, fsynced) before the id is used.

        Raises StoreError (the old counter stays on disk) when not even that can be written."""
        n = self._next
        try:
            self.with_reserve(lambda: atomic_write_json(self.root / STATE, {"next_counter": n + 1}))
        except OSError as e:
            what = "cannot record the capture counter"
            self.alarm = (
                self._full_alarm(what) if is_enospc(e) else f"STOPPED: {what} ({e.strerror or e}); captures resume when it can be written"
            )
            raise StoreError(self.alarm) from e
        self._next = n + 1
        return f"{n:06d}-{dt.datetime.now(dt.timezone.utc):%Y%m%dT%H%M%SZ}"

    # ---- disk --------------------------------------------------------------------------------

    def disk_free(self) -> int:
        return int(self._free_bytes(self.root))

    def disk_ok(self) -> bool:
        """True when the disk is above its threshold; otherwise sets `alarm` (cleared once space is back)."""
        return self.room_for(0)

    def room_for(self, need_bytes: int) -> bool:
        """True when a capture of `need_bytes` can be written whole: the disk is above its threshold and
        the reserve of that size is held. Otherwise sets `alarm` ("STOPPED: disk full ...") and returns False."""
        free = self.disk_free()
        if free < self.min_free_bytes:
            self.alarm = (
                f"{DISK_FULL}: {free / 1e9:.2f} GB free, below the {self.min_free_bytes / 1e9:.2f} GB threshold; "
                "captures resume when space is freed"
            )
            return False
        try:
            held = need_bytes <= 0 or self._hold_reserve(need_bytes)
        except OSError as e:
            self.alarm = f"STOPPED: the store cannot be written ({e.strerror or e}); captures resume when it can"
            return False
        if not held:
            self.alarm = self._full_alarm(f"no room to reserve {need_bytes / 1e6:.1f} MB for the next capture")
            return False
        self.alarm = ""
        return True

    def _full_alarm(self, what: str) -> str:
        return f"{DISK_FULL}: {what}; captures resume when space is freed"

    def _hold_reserve(self, size: int) -> bool:
        path = self.root / RESERVE
        try:
            if path.stat().st_size >= size:
                return True
        except FileNotFoundError:
            pass
        tmp = self.root / f"{RESERVE}.tmp"
        try:
            _allocate(tmp, size)
            os.replace(tmp, path)
        except OSError as e:
            tmp.unlink(missing_ok=True)
            if is_enospc(e):
                return False
            raise
        return True

    def release_reserve(self) -> bool:
        """Give the reserve back to the filesystem; False when none was held."""
        try:
            (self.root / RESERVE).unlink()
        except FileNotFoundError:
            return False
        return True

    def with_reserve(self, write: Callable[[], object]):
        """Run `write`; on ENOSPC release the reserve (the disk filled behind our back) and run it once more."""
        try:
            return write()
        except OSError as e:
            if not is_enospc(e) or not self.release_reserve():
                raise
            self.alarm = self._full_alarm("the disk filled up; the capture in flight was written into its reserve")
            return write()

    # ---- writing -----------------------------------------------------------------------------

    def commit(self, capture_id: str, frames: Sequence[FrameData], meta: dict, backgrounds: dict | None = None) -> StoredCapture:
        """Write, verify and publish a capture (with the rig's empty-rig `backgrounds` per camera, when
        given). On failure nothing appears under captures/ and the error is raised."""
        incoming = self.root / INCOMING / capture_id
        final = self.root / CAPTURES / capture_id
        if final.exists():
            raise StoreError(f"capture id {capture_id} is already in the store; ids are never reused")

        def write() -> None:
            try:
                write_capture(incoming, frames, backgrounds=backgrounds, meta={**meta, "capture_id": capture_id})
                os.rename(incoming, final)
                fsync_dir(final.parent)
                fsync_dir(incoming.parent)
            except BaseException:
                shutil.rmtree(incoming, ignore_errors=True)
                raise

        try:
            self.with_reserve(write)
        except OSError as e:
            if is_enospc(e):
                self.alarm = self._full_alarm(f"capture {capture_id} did not fit even into its reserve")
            raise
        return StoredCapture(capture_id, final, "committed")

    def quarantine(
        self, capture_id: str, reason: str, frames: Sequence[FrameData] = (), meta: dict | None = None, detail: dict | None = None
    ) -> StoredCapture:
        """Keep what there is of a bad capture, with its reason, under quarantine/<id>.

        The frames are written when the disk allows; the reason file always is (it is a few
        hundred bytes). Raises StoreError only when not even the reason can be written.
        """
        staging = self.root / INCOMING / capture_id
        final = self._free_name(self.root / QUARANTINE / capture_id)
        record = {"capture_id": capture_id, "reason": reason, "time_utc": _now_utc(), **(detail or {})}
        shutil.rmtree(staging, ignore_errors=True)
        if frames:

            def write_frames() -> None:
                try:
                    write_capture(staging, frames, meta={**(meta or {}), "capture_id": capture_id, "quarantined": reason})
                except BaseException:
                    shutil.rmtree(staging, ignore_errors=True)
                    raise

            try:
                self.with_reserve(write_frames)
            except (OSError, CaptureError) as e:
                record["frames_not_saved"] = f"{len(frames)} frames could not be written: {getattr(e, 'strerror', None) or e}"

        def write_reason() -> None:
            staging.mkdir(exist_ok=True)
            atomic_write_json(staging / REASON, record)
            os.rename(staging, final)
            fsync_dir(final.parent)
            fsync_dir(staging.parent)

        try:
            self.with_reserve(write_reason)
        except OSError as e:
            shutil.rmtree(staging, ignore_errors=True)
            raise StoreError(f"could not quarantine capture {capture_id} ({reason}): {e.strerror or e}") from e
        return StoredCapture(capture_id, final, "quarantined", reason)

    # ---- recovery and reading ----------------------------------------------------------------

    def _recover_incoming(self) -> list[StoredCapture]:
        """Move whatever a crash left in .incoming/ to quarantine/ with a reason."""
        out = []
        incoming = self.root / INCOMING
        for p in sorted(incoming.iterdir()):
            name = p.name.lstrip(".")
            m = _ID.match(name)
            capture_id = m.group(0) if m else name
            if p.is_file():
                p.unlink()  # an atomic write's temp file: never published under a real name
                continue
            if p.name.endswith(IMPORTING):
                shutil.rmtree(p)  # a half-copied import: its source is still whole in the spill and is imported again
                continue
            final = self._free_name(self.root / QUARANTINE / capture_id)
            record = {
                "capture_id": capture_id,
                "reason": "left in .incoming/ by an interrupted write (crash, kill or power loss); never committed",
                "time_utc": _now_utc(),
                "files": sorted(str(f.relative_to(p)) for f in p.rglob("*") if f.is_file()),
            }
            try:
                atomic_write_json(p / REASON, record)
            except OSError as e:
                if not is_enospc(e):
                    raise  # without a reason.json the entry still moves: quarantine_reason() then says why
            os.rename(p, final)
            out.append(StoredCapture(capture_id, final, "quarantined", record["reason"]))
        for leftover in self.root.glob(f".{STATE}.*.tmp"):
            leftover.unlink()
        if out:
            fsync_dir(self.root / QUARANTINE)
            fsync_dir(incoming)
        return out

    def _free_name(self, path: Path) -> Path:
        k = 1
        out = path
        while out.exists():
            out = path.with_name(f"{path.name}.{k}")
            k += 1
        return out

    def capture_ids(self) -> list[str]:
        return sorted(p.name for p in (self.root / CAPTURES).iterdir() if p.is_dir() and not p.name.startswith("."))

    def quarantined_ids(self) -> list[str]:
        return sorted(p.name for p in (self.root / QUARANTINE).iterdir() if p.is_dir())

    def quarantine_reason(self, capture_id: str) -> str:
        try:
            return json.loads((self.root / QUARANTINE / capture_id / REASON).read_text())["reason"]
        except (FileNotFoundError, ValueError, KeyError, TypeError):
            return "left by an interrupted write; its reason.json could not be written (disk full) or is damaged"

    def read(self, capture_id: str) -> Capture:
        """A stored capture, every sha256 verified."""
        return read_capture(self.root / CAPTURES / capture_id, verify=True)

    # ---- the spill ---------------------------------------------------------------------------

    def import_spill(self, spill: Spill) -> tuple[list[StoredCapture], str]:
        """Move the spilled captures into the store under their ids, oldest first; (what became of each, and one
        sentence when the store could not take them all: the rest wait in the spill).

        Each entry is copied into .incoming/, verified, renamed into captures/ (an invalid capture, or a spilled
        copy that does not verify, into quarantine/ with its reason) and only then removed from the spill. A crash
        anywhere leaves the entry in the spill and running this again finishes the job: a store copy that is
        already there and verifies is kept, a half-copied one is deleted when the store opens."""
        spill.clean()
        out: list[StoredCapture] = []
        for src, capture_id, damage in spill.entries():
            try:
                out.append(self._import_one(spill, src, capture_id, damage))
            except (OSError, CaptureError) as e:
                left = len(spill.entries())
                return out, (
                    f"could not import spilled capture {capture_id} into {self.root} ({getattr(e, 'strerror', None) or e}); "
                    f"{left} spilled capture(s) wait in {spill.dir}"
                )
        return out, ""

    def _import_one(self, spill: Spill, src: Path, capture_id: str, damage: str) -> StoredCapture:
        cap = None
        if not damage:
            try:
                cap = read_capture(src, verify=True)
                if cap.meta.get("capture_id") != capture_id:
                    raise CaptureError(f"its transforms.json names capture {cap.meta.get('capture_id')!r}")
            except (CaptureError, OSError, ValueError) as e:
                damage = f"its spilled copy does not verify ({e})"
        reason = damage or (cap.meta.get("quarantined", "") if cap is not None else "")
        final = self.root / CAPTURES / capture_id
        done = None
        if reason:
            done = next(
                (
                    StoredCapture(capture_id, q, "quarantined", reason)
                    for q in sorted((self.root / QUARANTINE).glob(f"{capture_id}*"))
                    if _reason_record(q).get("spill") == str(src)
                ),
                None,
            )
        elif final.exists():
            try:
                same = read_capture(final, verify=True).meta.get("sha256") == cap.meta.get("sha256")
            except (CaptureError, OSError, ValueError):
                same = False
            if same:  # imported before a crash that came ahead of the spill entry's removal
                done = StoredCapture(capture_id, final, "committed", "already in the store")
            else:
                reason = f"the store already holds a different capture {capture_id}"
        if done is None:
            done = self.with_reserve(lambda: self._copy_in(src, capture_id, reason))
        spill.discard(src)
        return done

    def _copy_in(self, src: Path, capture_id: str, reason: str) -> StoredCapture:
        staging = self.root / INCOMING / f"{capture_id}{IMPORTING}"
        shutil.rmtree(staging, ignore_errors=True)
        try:
            _copy_tree(src, staging)
            if reason:
                final = self._free_name(self.root / QUARANTINE / capture_id)
                atomic_write_json(staging / REASON, {"capture_id": capture_id, "reason": reason, "time_utc": _now_utc(), "spill": str(src)})
            else:
                final = self.root / CAPTURES / capture_id
                read_capture(staging, verify=True)
            os.rename(staging, final)
            fsync_dir(final.parent)
            fsync_dir(staging.parent)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        return StoredCapture(capture_id, final, "quarantined" if reason else "committed", reason)


def default_spill_dir() -> Path:
    """`$XDG_STATE_HOME/cadsplat/spill` (else `~/.local/state/cadsplat/spill`): the user's state, which on an
    appliance lies on the system disk, not on the store's filesystem (a sibling of the store would go read-only with it)."""
    state = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(state) / "cadsplat" / "spill"


DISCARD = ".discard"  # suffix of a spill entry being removed (its store copy verifies)
_HALF_SPILLED = "left half-written in the spill by an interrupted write (crash, kill or power loss)"


class Spill:
    """Captures a store could not take before the rig stopped, kept for it on another filesystem.

    Layout: `<root>/<store name>-<hash of its absolute path>/<capture id>/`, each entry a capture in the store's
    own format (calibration.capture, sha256 of every file; `quarantined` in its meta when it was invalid), so
    one spill directory serves several stores. Nothing is created until the first capture is spilled.
    """

    def __init__(self, root: str | os.PathLike, store_root: str | os.PathLike) -> None:
        self.root = Path(root)
        store = Path(os.path.abspath(store_root))
        self.dir = self.root / f"{store.name}-{hashlib.sha256(str(store).encode()).hexdigest()[:10]}"

    def write(self, capture_id: str, frames: Sequence[FrameData], meta: dict, backgrounds: dict | None = None) -> Path:
        """Write one capture atomically (fsynced, read back, verified); raises OSError or CaptureError when the spill cannot take it."""
        path = self.dir / capture_id
        write_capture(path, frames, backgrounds=backgrounds, meta={**meta, "capture_id": capture_id})
        return path

    def entries(self) -> list[tuple[Path, str, str]]:
        """(path, capture id, damage) of every entry waiting for the store, oldest first; `damage` names a half-written one."""
        try:
            names = sorted(os.listdir(self.dir))
        except (FileNotFoundError, NotADirectoryError):
            return []
        out = []
        for name in names:
            path = self.dir / name
            if name.endswith(DISCARD) or not path.is_dir():
                continue
            m = _ID.match(name.lstrip("."))
            if name.startswith("."):
                out.append((path, m.group(0) if m else name.lstrip("."), _HALF_SPILLED))
            else:
                out.append((path, name, ""))
        return sorted(out, key=lambda e: (e[1], e[0].name))

    def discard(self, entry: Path) -> None:
        """Remove an entry the store now holds: renamed aside first (one atomic step), then deleted."""
        gone = entry.with_name(f".{entry.name.lstrip('.')}{DISCARD}")
        shutil.rmtree(gone, ignore_errors=True)
        os.rename(entry, gone)
        fsync_dir(self.dir)
        shutil.rmtree(gone, ignore_errors=True)

    def clean(self) -> None:
        """Delete what an interrupted `discard` left."""
        for p in self.dir.glob(f".*{DISCARD}") if self.dir.is_dir() else ():
            shutil.rmtree(p, ignore_errors=True)


def _copy_tree(src: Path, dst: Path) -> None:
    """Copy a capture directory file by file, each written durably, then make its directories durable."""
    dirs = [dst, *(dst / d.relative_to(src) for d in sorted(p for p in src.rglob("*") if p.is_dir()))]
    for d in dirs:
        os.mkdir(d)
    for f in sorted(p for p in src.rglob("*") if p.is_file()):
        atomic_write_bytes(dst / f.relative_to(src), f.read_bytes())
    for d in reversed(dirs):
        fsync_dir(d)


def _reason_record(entry: Path) -> dict:
    try:
        record = json.loads((entry / REASON).read_text())
    except (OSError, ValueError):
        return {}
    return record if isinstance(record, dict) else {}


def _now_utc() -> str:
    return dt.datetime.now(dt.timezone.utc).isoformat(timespec="milliseconds")

from __future__ import annotations

import errno
import json
import os
import shutil

import numpy as np
import pytest

import calibration.capture as capture_mod
from calibration.camera import Camera
from calibration.capture import FrameData
from rig.store import CAPTURES, IMPORTING, INCOMING, QUARANTINE, STATE, CaptureStore, Spill
from tests.rig.conftest import assert_store_sound


def _frames(n: int = 2, seed: int = 0) -> list[FrameData]:
    rng = np.random.default_rng(seed)
    cam = Camera.from_fov(1.0, 32, 24)
    return [FrameData(f"cam{i}", rng.integers(0, 255, (24, 32, 3), dtype=np.uint8), cam, f"cam{i}", 1000 + i) for i in range(n)]


def test_commit_is_verified_and_carries_ids(store_root):
    store = CaptureStore(store_root, min_free_bytes=0)
    cid = store.reserve_id()
    out = store.commit(cid, _frames(), {"rig_id": "line-3", "calibration_id": "cal-7", "trigger": {"seq": 4}})
    assert out.status == "committed" and out.path == store_root / CAPTURES / cid
    cap = store.read(cid)
    assert cap.meta["rig_id"] == "line-3" and cap.meta["calibration_id"] == "cal-7" and cap.meta["trigger"]["seq"] == 4
    assert len(cap.meta["sha256"]) == 2 and [f.timestamp_ns for f in cap.frames] == [1000, 1001]
    assert_store_sound(store_root, [cid])


def test_ids_are_never_reused_even_when_the_state_file_is_lost(store_root):
    store = CaptureStore(store_root, min_free_bytes=0)
    a = store.reserve_id()  # reserved, never committed (a crash right after reserving)
    b = store.reserve_id()
    store.commit(b, _frames(), {})
    assert a[:6] == "000000" and b[:6] == "000001"
    again = CaptureStore(store_root)
    assert again.reserve_id()[:6] == "000002"  # the persisted counter survives a restart
    again.quarantine(again.reserve_id(), "test")  # 000003, quarantined
    (store_root / STATE).unlink()
    c = CaptureStore(store_root).reserve_id()
    assert c[:6] == "000004"  # state lost: rebuilt from every id on disk, stored or quarantined


def test_restart_moves_leftover_incoming_to_quarantine_with_a_reason(store_root):
    store = CaptureStore(store_root, min_free_bytes=0)
    cid = store.reserve_id()
    half = store_root / INCOMING / f".{cid}.abc123.incoming" / "images"
    half.mkdir(parents=True)
    (half / "cam0.png").write_bytes(b"\x89PNG truncated")
    (store_root / INCOMING / ".tmpfile.tmp").write_bytes(b"x")
    again = CaptureStore(store_root, min_free_bytes=0)
    assert [r.capture_id for r in again.recovered] == [cid]
    assert again.quarantined_ids() == [cid]
    reason = json.loads((store_root / QUARANTINE / cid / "reason.json").read_text())
    assert "interrupted write" in reason["reason"] and reason["files"] == ["images/cam0.png"]
    assert not any((store_root / INCOMING).iterdir())
    assert_store_sound(store_root, [])


def test_enospc_while_writing_leaves_nothing_half_written(store_root, monkeypatch):
    store = CaptureStore(store_root, min_free_bytes=0)
    real = capture_mod.atomic_write_bytes
    calls = {"n": 0}

    def full_disk(path, data):
        calls["n"] += 1
        if calls["n"] == 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return real(path, data)

    monkeypatch.setattr(capture_mod, "atomic_write_bytes", full_disk)
    cid = store.reserve_id()
    with pytest.raises(OSError) as e:
        store.commit(cid, _frames(3), {})
    assert e.value.errno == errno.ENOSPC and "disk full" in store.alarm
    assert store.capture_ids() == []
    q = store.quarantine(cid, "disk full while writing", _frames(3), {})
    assert q.status == "quarantined" and store.quarantine_reason(cid) == "disk full while writing"
    assert_store_sound(store_root, [])


def test_low_disk_stops_captures_and_clears_when_space_returns(store_root):
    free = {"bytes": 10 << 30}
    store = CaptureStore(store_root, min_free_bytes=2 << 30, free_bytes=lambda p: free["bytes"])
    cid = store.reserve_id()
    store.commit(cid, _frames(), {})
    free["bytes"] = 1 << 30
    assert not store.disk_ok() and "below the 2.15 GB threshold" in store.alarm
    assert store.capture_ids() == [cid]  # stored captures untouched
    free["bytes"] = 5 << 30
    assert store.disk_ok() and store.alarm == ""


@pytest.fixture
def tiny_tmpfs(tmp_path):
    """A real 256 kB tmpfs (real ENOSPC from the kernel); skipped where mounting is not allowed."""
    import subprocess

    mnt = tmp_path / "tmpfs"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mnt)], capture_output=True)
    if r.returncode != 0:
        pytest.skip("cannot mount a tmpfs here (needs root / CAP_SYS_ADMIN)")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def test_a_full_tmpfs_loses_no_capture_says_stopped_once_and_resumes(tiny_tmpfs):
    """Issue 16 (2): on a tiny tmpfs captures were "quarantined" with no frames, an ENOSPC on store.json ended
    the run, and refusals never said the rig had stopped."""
    from rig.triggers import SoftwareTrigger
    from tests.rig.conftest import make_acquisition, pattern_cameras

    store_root = tiny_tmpfs / "store"
    acq = make_acquisition(store_root, pattern_cameras(3, 96, 72), store=CaptureStore(store_root, min_free_bytes=10_000))
    trig = SoftwareTrigger()
    outs = [acq.handle(trig.fire()) for _ in range(40)]
    statuses = [o.status for o in outs]
    assert "committed" in statuses and "refused" in statuses
    assert set(statuses) == {"committed", "refused"}  # nothing quarantined without its frames, nothing failed
    stops = [o for o in outs if o.state_change == "stopped"]
    assert len(stops) == 1 and stops[0].reason.startswith("STOPPED: disk full")
    committed = [o.capture_id for o in outs if o.status == "committed"]
    assert assert_store_sound(store_root, committed) == committed
    # space returns: the rig says so and captures again
    shutil.rmtree(store_root / CAPTURES / committed[0])
    again = acq.handle(trig.fire())
    acq.close()
    assert again.status == "committed" and again.state_change == "resumed"
    assert_store_sound(store_root, committed[1:] + [again.capture_id])


def _spilled(tmp_path, n: int = 2) -> tuple[CaptureStore, Spill, list[str]]:
    """A store whose ids were reserved but whose captures went to the spill (the store was read-only)."""
    store = CaptureStore(tmp_path / "store", min_free_bytes=0)
    spill = Spill(tmp_path / "spill", store.root)
    ids = [store.reserve_id() for _ in range(n)]
    for k, cid in enumerate(ids):
        spill.write(cid, _frames(seed=k), {"rig_id": "line-3"})
    return store, spill, ids


def test_spilled_captures_are_imported_under_their_ids_and_the_spill_emptied(tmp_path):
    store, spill, ids = _spilled(tmp_path)
    assert [cid for _, cid, _ in spill.entries()] == ids and spill.dir.parent == tmp_path / "spill"
    imported, problem = store.import_spill(spill)
    assert problem == "" and [(r.capture_id, r.status) for r in imported] == [(i, "committed") for i in ids]
    assert assert_store_sound(store.root, ids) == ids and store.read(ids[0]).meta["rig_id"] == "line-3"
    assert spill.entries() == [] and list(spill.dir.iterdir()) == []


def test_import_is_idempotent_after_a_crash_between_copy_and_delete(tmp_path, monkeypatch):
    store, spill, ids = _spilled(tmp_path)

    def crash(_entry):
        raise KeyboardInterrupt("killed after the store copy, before the spill entry was removed")

    monkeypatch.setattr(spill, "discard", crash)
    with pytest.raises(KeyboardInterrupt):
        store.import_spill(spill)
    monkeypatch.undo()
    assert store.capture_ids() == ids[:1] and len(spill.entries()) == 2
    again = CaptureStore(store.root, min_free_bytes=0)
    imported, problem = again.import_spill(spill)
    assert problem == "" and [r.reason for r in imported] == ["already in the store", ""]
    assert assert_store_sound(store.root, ids) == ids and again.quarantined_ids() == [] and spill.entries() == []
    assert again.import_spill(spill) == ([], "")


def test_a_half_copied_import_is_dropped_on_open_and_imported_again(tmp_path):
    store, spill, ids = _spilled(tmp_path, 1)
    half = store.root / INCOMING / f"{ids[0]}{IMPORTING}" / "images"
    half.mkdir(parents=True)
    (half / "cam0.png").write_bytes(b"\x89PNG truncated")  # killed mid-copy
    again = CaptureStore(store.root, min_free_bytes=0)
    assert again.recovered == [] and not any((store.root / INCOMING).iterdir())
    assert again.import_spill(spill)[0][0].status == "committed" and assert_store_sound(store.root, ids) == ids


def test_a_damaged_spilled_capture_is_quarantined_with_its_reason(tmp_path):
    store, spill, ids = _spilled(tmp_path)
    png = spill.dir / ids[1] / "images" / "cam0.png"
    damaged = png.read_bytes()[:-20]
    png.write_bytes(damaged)
    half = spill.dir / f".{ids[1][:6]}9-20260101T000000Z.abc.incoming"  # a spill write cut short by a kill
    half.mkdir()
    imported, problem = store.import_spill(spill)
    assert problem == "" and [r.status for r in imported] == ["committed", "quarantined", "quarantined"]
    assert "spilled copy does not verify" in imported[1].reason and "interrupted write" in imported[2].reason
    assert store.capture_ids() == ids[:1] and ids[1] in store.quarantined_ids() and spill.entries() == []
    assert (store.root / QUARANTINE / ids[1] / "images" / "cam0.png").read_bytes() == damaged  # kept as it was, with its reason


def test_import_into_a_store_that_is_still_read_only_leaves_the_spill_as_it_is(tmp_path):
    from tests.faultfs import FaultyDisk

    store, spill, ids = _spilled(tmp_path)
    with FaultyDisk(store.root, fail_at=1, errno_=errno.EROFS, persistent=True).active():
        imported, problem = store.import_spill(spill)
    assert imported == [] and f"could not import spilled capture {ids[0]}" in problem and "Read-only file system" in problem
    assert f"2 spilled capture(s) wait in {spill.dir}" in problem and "\n" not in problem
    assert store.capture_ids() == [] and len(spill.entries()) == 2 and not any((store.root / INCOMING).iterdir())


def test_a_spilled_invalid_capture_goes_to_quarantine_once_with_its_reason(tmp_path, monkeypatch):
    store = CaptureStore(tmp_path / "store", min_free_bytes=0)
    spill = Spill(tmp_path / "spill", store.root)
    cid = store.reserve_id()
    spill.write(cid, _frames(1), {"quarantined": "no frame from cam1"})
    monkeypatch.setattr(spill, "discard", lambda _e: (_ for _ in ()).throw(KeyboardInterrupt("killed before the spill entry was removed")))
    with pytest.raises(KeyboardInterrupt):
        store.import_spill(spill)
    monkeypatch.undo()
    imported, problem = store.import_spill(spill)
    assert problem == "" and [(r.capture_id, r.status, r.reason) for r in imported] == [(cid, "quarantined", "no frame from cam1")]
    assert store.quarantined_ids() == [cid] and store.quarantine_reason(cid) == "no frame from cam1"  # one entry, not two
    assert store.capture_ids() == [] and spill.entries() == []


def test_one_writer_holds_the_store_for_its_life_and_a_reader_can_tell(store_root):
    """`lock_store` refuses a second writer naming the first (another process); `writer_holds` tells a reader that
    .incoming/ holds captures in flight, and never creates a lock file on a store nobody locked."""
    import subprocess
    import sys

    from calibration.guard import LockHeld
    from rig.store import LOCK, lock_store, writer_holds
    from tests.conftest import REPO

    assert not writer_holds(store_root) and not (store_root / LOCK).exists()
    code = f"from rig.store import lock_store; lock_store({str(store_root)!r}, 'rig watch'); print('held', flush=True); input()"
    rig = subprocess.Popen(
        [sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(REPO)}
    )
    try:
        assert rig.stdout.readline().strip() == "held"
        assert writer_holds(store_root)
        with pytest.raises(LockHeld, match=rf"in use by rig watch \(pid {rig.pid}\)"):
            lock_store(store_root, "store import-spill")
    finally:
        rig.communicate("\n", timeout=60)
    assert not writer_holds(store_root)
    lock_store(store_root, "store import-spill").release()

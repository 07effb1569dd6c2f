"""Fault injection (issue 16): ENOSPC and EROFS at every write site of the store, the keeper and the
service in turn. After each: every capture committed and verifying or refused and counted, nothing
half-written, one sentence per failure. (SIGKILL: tests/deploy/test_kill_appliance.py.)"""

from __future__ import annotations

import errno
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from calibration.calibfile import CalibrationDoc, CalibrationStore
from calibration.camera import Camera
from calibration.keeper import Keeper
from deploy.commands.store import verify_store
from deploy.jobs import STEPS
from deploy.service import PipelineService
from rig.store import CaptureStore, Spill
from rig.triggers import SoftwareTrigger
from tests.faultfs import FaultyDisk
from tests.rig.conftest import assert_store_sound, make_acquisition

TRIGGERS = 2  # per run; benchmarks.bench_faults runs 3


def spill_of(root: Path) -> Spill:
    """The spill the fault runs use: a sibling of the store, outside the faulty disk's root (another filesystem)."""
    return Spill(root.with_name(f"{root.name}.spill"), root)


def _run_rig(root: Path, disk: FaultyDisk, *, heal: bool = False, triggers: int = TRIGGERS) -> tuple[list, object]:
    """A reference and `triggers` captures on pattern cameras under `disk`'s faults; with `heal`, the fault then
    clears and one more trigger comes (what was held in memory is written then). Held captures spill to `spill_of(root)`."""
    acq = make_acquisition(root, spill=spill_of(root))
    trig = SoftwareTrigger()
    outs = []
    with disk.active():
        try:
            outs.append(acq.take_reference("test"))
            outs += [acq.handle(trig.fire()) for _ in range(triggers)]
            if heal:
                disk.fail_at = None
                outs += acq.flush_held()
                outs.append(acq.handle(trig.fire()))
        finally:
            outs += acq.close()
    return outs, acq


def _rig_sites(tmp_path) -> int:
    disk = FaultyDisk(tmp_path / "count")
    outs, _ = _run_rig(tmp_path / "count", disk)
    assert [o.status for o in outs] == ["reference"] + ["committed"] * TRIGGERS
    return len(disk.calls)


def _assert_nothing_lost(root: Path, outs) -> dict:
    """The acceptance invariant after a fault: every trigger committed (and verifying) or refused (counted, one
    sentence); reopening the store leaves nothing half-written; `store verify` finds no problem."""
    statuses = [o.status for o in outs]
    assert set(statuses) <= {"reference", "committed", "refused"}, [(o.status, o.reason) for o in outs]
    assert len(set(o.capture_id for o in outs if o.status == "committed")) == statuses.count("committed")
    for o in outs:
        if o.status == "refused":
            assert o.reason and "\n" not in o.reason and "Traceback" not in o.reason
    committed = [o.capture_id for o in outs if o.status == "committed"]
    CaptureStore(root, min_free_bytes=0)  # the next start cleans up whatever the fault left
    assert assert_store_sound(root, committed) == sorted(committed)
    counts, problems = verify_store(root)
    assert problems == [] and counts["verified"] == len(committed)
    return {s: statuses.count(s) for s in set(statuses)}


@pytest.mark.parametrize("mode", ["transient", "filled"])
def test_enospc_at_every_write_site_of_the_rig_loses_no_capture(tmp_path, mode):
    n_sites = _rig_sites(tmp_path)
    assert n_sites >= 4 * (TRIGGERS + 1)
    refused = 0
    for n in range(1, n_sites + 1):
        root = tmp_path / f"{mode}-{n}"
        disk = FaultyDisk(root, fail_at=n) if mode == "transient" else FaultyDisk(root, fill_at=n)
        outs, acq = _run_rig(root, disk)
        counts = _assert_nothing_lost(root, outs)
        refused += counts.get("refused", 0)
        if mode == "filled" and counts.get("refused"):
            assert acq.stopped.startswith("STOPPED: disk full") or outs[0].status == "refused"
    if mode == "filled":
        assert refused > 0  # the disk did fill: later captures were refused, before their frames were taken


def test_erofs_at_every_write_site_holds_the_frames_until_the_store_is_writable(tmp_path):
    """The filesystem goes read-only at each write site in turn, then comes back: a capture the fault caught
    mid-write is held in memory and committed once the store is writable; later ones are refused, said once."""
    n_sites = _rig_sites(tmp_path)
    held = 0
    for n in range(1, n_sites + 1):
        root = tmp_path / f"ro-{n}"
        outs, _ = _run_rig(root, FaultyDisk(root, fail_at=n, errno_=errno.EROFS, persistent=True), heal=True)
        statuses = [o.status for o in outs]
        held += statuses.count("held")
        assert "failed" not in statuses and statuses.count("held") == sum(
            1 for o in outs if o.status == "committed" and "written after" in o.reason
        )
        assert all("\n" not in o.reason for o in outs)
        settled = [o for o in outs if o.status != "held"]
        _assert_nothing_lost(root, settled)
        assert spill_of(root).entries() == []  # each spill copy was dropped once the store took the capture
    assert held > 0  # some faults did land mid-capture


def _next_start(root: Path) -> list:
    """What the rig's next start does with the store: reopen it and import what waits in the spill."""
    imported, problem = CaptureStore(root, min_free_bytes=0).import_spill(spill_of(root))
    assert problem == ""
    return imported


def test_erofs_until_the_rig_stops_spills_the_held_captures_and_the_next_start_imports_them(tmp_path):
    """The filesystem goes read-only at each write site in turn and stays so until the rig stops: a capture the
    fault caught mid-write is spilled (never failed); the next start imports it under its id and `store verify` passes."""
    n_sites = _rig_sites(tmp_path)
    spilled = 0
    for n in range(1, n_sites + 1):
        root = tmp_path / f"ro-{n}"
        outs, acq = _run_rig(root, FaultyDisk(root, fail_at=n, errno_=errno.EROFS, persistent=True))
        statuses = [o.status for o in outs]
        assert "failed" not in statuses and statuses.count("held") == statuses.count("spilled") == acq.counts["spilled"]
        for o in outs:
            if o.status == "spilled":
                assert "\n" not in o.reason and str(spill_of(root).dir) in o.reason
        spilled += statuses.count("spilled")
        ids = [o.capture_id for o in outs if o.status == "spilled"]
        imported = _next_start(root)
        assert [(r.capture_id, r.status) for r in imported] == [(i, "committed") for i in ids]
        settled = [o for o in outs if o.status not in ("held", "spilled")] + [o for o in outs if o.status == "spilled"]
        _assert_nothing_lost(root, [replace(o, status="committed") if o.status == "spilled" else o for o in settled])
        assert verify_store(root, spill_of(root).root)[1] == [] and _next_start(root) == []
    assert spilled > 0  # some faults did land mid-capture


def test_a_spill_that_cannot_be_written_either_fails_the_capture_in_one_sentence(tmp_path):
    for n in range(1, _rig_sites(tmp_path) + 1):
        root = tmp_path / f"ro-{n}"
        spill_disk = FaultyDisk(spill_of(root).root, fail_at=1, errno_=errno.EROFS, persistent=True)
        with spill_disk.active():
            outs, acq = _run_rig(root, FaultyDisk(root, fail_at=n, errno_=errno.EROFS, persistent=True))
        if acq.counts["failed"]:
            break
    failed = [o for o in outs if o.status == "failed"]
    assert failed and acq.counts["spilled"] == 0
    assert all("\n" not in o.reason and "could not take it either (Read-only file system); its frames are lost" in o.reason for o in failed)


def test_store_counter_survives_enospc(tmp_path):
    root = tmp_path / "s"
    store = CaptureStore(root, min_free_bytes=0)
    first = store.reserve_id()
    with FaultyDisk(root, fail_at=1, persistent=True).active():
        with pytest.raises(Exception) as e:
            store.reserve_id()
    assert "STOPPED: disk full: cannot record the capture counter" in str(e.value)
    assert json.loads((root / "store.json").read_text())["next_counter"] == 1
    assert CaptureStore(root, min_free_bytes=0).reserve_id()[:6] == "000001" and first[:6] == "000000"


def _keeper_flow(root: Path) -> None:
    cams = {f"cam{i}": Camera.from_fov(1.0, 64, 48) for i in range(2)}
    store = CalibrationStore(root / "calibration.json")
    store.commit(CalibrationDoc(cams, source="board"))
    keeper = Keeper(root / "calibration.json")
    frames = {n: np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8) for n in cams}
    keeper.set_reference(frames)
    keeper.check(frames, capture="c1")
    store.commit(CalibrationDoc(cams, source="board"))


def test_enospc_at_every_write_site_of_the_keeper_leaves_a_readable_calibration(tmp_path):
    count = FaultyDisk(tmp_path / "count")
    (tmp_path / "count").mkdir()
    with count.active():
        _keeper_flow(tmp_path / "count")
    assert len(count.calls) >= 6
    for n in range(1, len(count.calls) + 1):
        root = tmp_path / f"k{n}"
        root.mkdir()
        with FaultyDisk(root, fail_at=n).active():
            try:
                _keeper_flow(root)  # a mkdir of a folder that exists meets no fault
            except OSError as e:
                assert e.errno == errno.ENOSPC and str(e).startswith("[Errno 28] No space left on device")
        left = [p.name for p in root.rglob("*") if p.name.endswith(".tmp")]
        assert not left, f"temp files left at site {n}: {left}"
        store = CalibrationStore(root / "calibration.json")
        if (root / "calibration.json").exists():
            store.load()  # the current calibration is whole
        for v in store.versions():
            store.load(v)  # and every version


class _Steps:
    """A pipeline whose steps write their outputs atomically under the job dir (as the real steps do)."""

    def __call__(self, step, job, work_dir: Path, previous):
        from calibration.fileio import atomic_write_json

        work_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_json(work_dir / f"{step}.json", {"step": step})
        return {"step": step}


def _captures(root: Path, n: int = 2) -> None:
    acq = make_acquisition(root)
    trig = SoftwareTrigger()
    for _ in range(n):
        assert acq.handle(trig.fire()).status == "committed"
    acq.close()


def test_enospc_at_every_write_site_of_the_service_stops_then_resumes(tmp_path):
    _captures(tmp_path / "store")
    count = FaultyDisk(tmp_path / "count")
    with count.active():
        svc = PipelineService(tmp_path / "store", tmp_path / "count", _Steps(), min_free_bytes=0)
        while svc.run_once():
            pass
    assert len(count.calls) >= 2 * len(STEPS)
    for n in range(1, len(count.calls) + 1):
        work = tmp_path / f"w{n}"
        events, free = [], {"b": 10 << 30}
        disk = FaultyDisk(work, fail_at=n, persistent=True)
        with disk.active():
            try:
                svc = PipelineService(
                    tmp_path / "store",
                    work,
                    _Steps(),
                    min_free_bytes=1 << 20,
                    resume_margin_bytes=1 << 20,
                    free_bytes=lambda _p: free["b"],
                    on_event=events.append,
                )
            except (RuntimeError, OSError) as e:  # the work dir or job store could not be created: one sentence, at start
                assert "\n" not in str(e) and ("cannot open the job store" in str(e) or "No space left" in str(e))
                continue
            for _ in range(10):
                svc.run_once()
            assert svc.state.startswith("STOPPED: disk full"), (n, svc.state)
            assert [e.kind for e in events].count("stopped") == 1
        # space is back: the service resumes and every capture becomes a finished job, none failed
        disk.fail_at = None
        free["b"] += 100 << 20
        with disk.active():
            for _ in range(10):
                svc.run_once()
        assert svc.state == "" and [e.kind for e in events].count("resumed") == 1
        assert [j.status for j in svc.jobs.jobs()] == ["done", "done"], n
        assert all(j.attempts <= 1 for j in svc.jobs.jobs())  # a full disk spends no attempt
        assert not list(work.rglob("*.tmp"))

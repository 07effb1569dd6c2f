from __future__ import annotations

import threading
import time

import numpy as np
import serial

from rig.acquisition import Thresholds, agree_photometry, brightness, validate_frames
from rig.camera import CameraError, CameraSettings, Frame, Health
from rig.replay import ReplayCamera, load_recordings
from rig.store import CaptureStore
from rig.synthetic_driver import PatternCamera, SyntheticRig, procedural_part
from rig.triggers import SerialTrigger, SoftwareTrigger, TriggerFilter, format_trigger_line
from tests.rig.conftest import assert_store_sound, make_acquisition, pattern_cameras


class Unpluggable(PatternCamera):
    """A pattern camera whose cable is pulled during its grab number `pull_at` and pushed back `away` grabs later."""

    def __init__(self, *a, pull_at: int, away: int, **kw):
        super().__init__(*a, **kw)
        self.pull_at, self.away, self.grabs, self.plugged = pull_at, away, 0, True

    def open(self):
        if not self.plugged:
            self.away -= 1
            self.plugged = self.away <= 0
            raise CameraError(f"{self.camera_id}: device not found")
        super().open()

    def grab(self, timeout_s):
        self.grabs += 1
        if self.grabs == self.pull_at:
            self.plugged = False
            self._open = False
            raise CameraError(f"{self.camera_id}: disconnected mid-transfer")
        return super().grab(timeout_s)

    def health(self):
        return Health(self.camera_id, self.plugged and self._open)


def test_validation_names_each_problem():
    th = Thresholds(sync_tolerance_ns=1_000_000, black_level=0.05, saturated_fraction=0.4)
    ok = np.full((8, 8, 3), 120, np.uint8)
    frames = {
        "a": Frame("a", ok, 0),
        "b": Frame("b", np.zeros_like(ok), 500_000),
        "c": Frame("c", np.full_like(ok, 255), 2_500_000),
        "d": Frame("d", ok[:4], 0),
    }
    sizes = dict.fromkeys("abcde", (8, 8))
    problems = validate_frames(frames, list("abcde"), sizes, th)
    assert problems == [
        "no frame from e",
        "b frame is black (mean 0.000)",
        "c frame is saturated (100% clipped)",
        "d frame is uint8 (4, 8, 3), expected uint8 (8, 8, 3)",
        "frames are 2.50 ms apart, beyond the 1.00 ms sync tolerance",
    ]
    assert validate_frames({"a": frames["a"]}, ["a"], sizes, th) == []
    assert brightness(ok) == (120 / 255, 0.0)


def test_camera_disappearing_mid_capture_is_quarantined_then_recovered(store_root):
    cams = pattern_cameras(3)
    cams[1] = Unpluggable("cam1", index=1, n=3, width=64, height=48, pull_at=3, away=2)
    acq = make_acquisition(store_root, cams)
    trig = SoftwareTrigger()
    outcomes = [acq.handle(trig.fire()) for _ in range(7)]
    acq.close()
    assert [o.status for o in outcomes] == ["committed"] * 2 + ["quarantined"] * 3 + ["committed"] * 2
    assert "cam1: cam1: disconnected mid-transfer" in outcomes[2].reason
    assert "device not found" in outcomes[3].reason
    stored = assert_store_sound(store_root, [o.capture_id for o in outcomes if o.status == "committed"])
    assert len(stored) == 4 and acq.store.quarantined_ids() == sorted(o.capture_id for o in outcomes[2:5])
    # the quarantined capture keeps the frames that did arrive
    q = store_root / "quarantine" / outcomes[2].capture_id
    assert sorted(p.name for p in (q / "images").iterdir()) == ["cam0.png", "cam2.png"]


def test_trigger_storm_1khz_for_2s_every_trigger_accounted(store_root):
    """2000 photo-eye lines in 2 s on a serial loop; the rig takes one capture per 100 ms at most."""
    port = serial.serial_for_url("loop://", timeout=0.05)
    src = SerialTrigger("loop://", open_port=lambda: port).start()
    acq = make_acquisition(store_root, trigger_filter=TriggerFilter(debounce_ns=0, min_interval_ns=100_000_000))

    def plc():
        t0 = time.monotonic()
        for seq in range(1, 2001):
            while time.monotonic() < t0 + seq * 1e-3:
                time.sleep(0.0002)
            port.write(format_trigger_line(seq, seq * 8))

    sender = threading.Thread(target=plc)
    sender.start()
    stop = threading.Event()
    outcomes = []
    runner = threading.Thread(target=acq.run, args=(src, stop), kwargs={"on_outcome": outcomes.append})
    runner.start()
    sender.join()
    deadline = time.monotonic() + 30
    while len(outcomes) < 2000 and time.monotonic() < deadline:
        time.sleep(0.05)
    stop.set()
    runner.join()
    src.stop()
    acq.close()
    f = acq.trigger_filter
    assert src.stats["events"] == 2000 and src.stats["garbage"] == 0
    assert f.received == 2000 and sum(acq.counts.values()) == 2000 and len(outcomes) == 2000
    assert acq.counts["dropped"] == f.too_soon + f.duplicates and f.missed == 0
    assert acq.counts["failed"] == 0
    committed = [o.capture_id for o in outcomes if o.status == "committed"]
    assert 10 <= len(committed) <= 21 and acq.taken == f.accepted - acq.counts["late"] - acq.counts["refused"]
    assert assert_store_sound(store_root, committed) == sorted(committed)


def test_low_disk_refuses_new_captures_and_keeps_stored_ones(store_root):
    free = {"b": 10 << 30}
    store = CaptureStore(store_root, min_free_bytes=1 << 30, free_bytes=lambda p: free["b"])
    acq = make_acquisition(store_root, store=store)
    trig = SoftwareTrigger()
    first = acq.handle(trig.fire())
    free["b"] = 100 << 20
    refused = acq.handle(trig.fire())
    free["b"] = 10 << 30
    third = acq.handle(trig.fire())
    acq.close()
    assert (first.status, refused.status, third.status) == ("committed", "refused", "committed")
    assert refused.reason.startswith("STOPPED: disk full") and refused.state_change == "stopped" and third.state_change == "resumed"
    assert assert_store_sound(store_root, [first.capture_id, third.capture_id]) == sorted([first.capture_id, third.capture_id])


def test_photometry_agrees_on_the_median_of_converged_settings():
    class Auto(PatternCamera):
        def __init__(self, cid, exposure):
            super().__init__(cid, width=32, height=24)
            self.auto_exposure, self.applied = exposure, None

        def configure(self, s):
            self.applied = s
            return CameraSettings(s.width, s.height, s.exposure_us or self.auto_exposure, s.iso or 200, s.white_balance_k or 5000)

    cams = [Auto("a", 8000), Auto("b", 12000), Auto("c", 9000)]
    locked = agree_photometry(cams, CameraSettings(32, 24))
    assert (locked.exposure_us, locked.iso, locked.white_balance_k) == (9000, 200, 5000)
    assert all(c.applied == locked for c in cams)


def test_replay_plays_stored_captures_back_identically(store_root, tmp_path):
    acq = make_acquisition(store_root)
    trig = SoftwareTrigger()
    originals = [acq.handle(trig.fire()).capture_id for _ in range(2)]
    acq.close()
    load_recordings.cache_clear()
    replay = [ReplayCamera(f"cam{i}", store_root / "captures") for i in range(3)]
    again = make_acquisition(tmp_path / "replayed", replay)
    replay_trigger = SoftwareTrigger()
    out = [again.handle(replay_trigger.fire(seq=s)) for s in (0, 1)]  # trigger seq s plays recording s mod 2
    again.close()
    assert [o.status for o in out] == ["committed", "committed"]
    for orig, new in zip(originals, out):
        a, b = acq.store.read(orig), again.store.read(new.capture_id)
        assert np.array_equal(a.image(1, undistort=False), b.image(1, undistort=False))
        np.testing.assert_allclose(a.camera(1).c2w, b.camera(1).c2w)


def test_synthetic_rig_captures_a_new_part_per_trigger(store_root):
    rig = SyntheticRig.from_mesh(procedural_part(), 3, width=96, height=72, jitter_ns=100_000)
    try:
        acq = make_acquisition(store_root, rig.drivers())
        trig = SoftwareTrigger()
        outs = [acq.handle(trig.fire()) for _ in range(2)]
        acq.close()
    finally:
        rig.close()
    assert [o.status for o in outs] == ["committed", "committed"]
    a, b = (acq.store.read(o.capture_id) for o in outs)
    assert [f.camera_id for f in a.frames] == ["cam00", "cam01", "cam02"]
    assert a.meta["camera_settings"]["cam00"]["exposure_us"] == 10_000
    assert a.meta["sync_spread_ns"] <= 200_000
    # a different part pose on the belt for each trigger, from the same fixed cameras
    assert np.abs(a.image(0) - b.image(0)).mean() > 0.01
    np.testing.assert_allclose(a.camera(0).c2w, b.camera(0).c2w)


def test_grab_errors_from_driver_bugs_quarantine_instead_of_crashing(store_root):
    class Buggy(PatternCamera):
        def grab(self, timeout_s):
            raise ZeroDivisionError("oops")

    cams = pattern_cameras(2)
    cams.append(Buggy("cam2", index=2, n=3, width=64, height=48))
    acq = make_acquisition(store_root, cams)
    out = acq.handle(SoftwareTrigger().fire())
    acq.close()
    assert out.status == "quarantined" and "driver error: ZeroDivisionError: oops" in out.reason
    try:
        Unpluggable("x", pull_at=1, away=1).grab(0.1)
    except CameraError as e:
        assert "disconnected" in str(e)


def test_enospc_mid_capture_is_written_into_the_reserve_and_committed(store_root, monkeypatch):
    """The disk fills behind the rig's back mid-capture: the reserve is released, the capture in
    flight is committed whole (its frames are not lost to a quarantine entry without them)."""
    import errno
    import os

    import calibration.capture as capture_mod

    real, calls = capture_mod.atomic_write_bytes, {"n": 0}

    def disk_full_once(path, data):
        calls["n"] += 1
        if calls["n"] == 5:  # the 2nd capture's 2nd image (3 images per capture)
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return real(path, data)

    monkeypatch.setattr(capture_mod, "atomic_write_bytes", disk_full_once)
    acq = make_acquisition(store_root)
    trig = SoftwareTrigger()
    outs = [acq.handle(trig.fire()) for _ in range(3)]
    acq.close()
    assert [o.status for o in outs] == ["committed", "committed", "committed"]
    assert acq.store.quarantined_ids() == []
    committed = [o.capture_id for o in outs]
    assert assert_store_sound(store_root, committed) == committed


def test_captures_record_the_calibration_they_were_taken_under(store_root):
    up = {"vector": [0.0, 0.0, 1.0], "source": "calibration", "detail": "board frame 'conveyor' lying face up on the conveyor"}
    acq = make_acquisition(
        store_root,
        calibration_id="calibration-v0003",
        calibration_uncertainty={"rotation_deg": 0.04, "translation_mm": 0.4},
        up_rig=up,
    )
    out = acq.handle(SoftwareTrigger().fire())
    acq.close()
    meta = acq.store.read(out.capture_id).meta
    assert meta["calibration_id"] == "calibration-v0003"
    assert meta["calibration_uncertainty"] == {"rotation_deg": 0.04, "translation_mm": 0.4}
    assert meta["up_rig"] == up  # the twin stands the part up by it


def test_the_loop_ends_at_max_captures_while_the_store_holds_none_of_them(store_root, tmp_path, monkeypatch):
    """The store goes read-only: every capture is held in memory. At `max_captures` the loop still ends (held
    captures count) instead of taking trigger after trigger, and the held ones go to the spill at close."""
    import errno

    from rig.store import Spill

    acq = make_acquisition(store_root, trigger_filter=TriggerFilter(debounce_ns=0), spill=Spill(tmp_path / "spill", store_root))

    def read_only(*_a, **_kw):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(acq.store, "commit", read_only)
    src = SoftwareTrigger()
    for _ in range(20):
        src.fire()
    stop = threading.Event()
    runner = threading.Thread(target=acq.run, args=(src, stop), kwargs={"max_captures": 3, "poll_s": 0.01})
    runner.start()
    runner.join(timeout=60)
    ended_by_itself = not runner.is_alive()
    stop.set()
    runner.join()
    outs = acq.close()
    assert ended_by_itself, "the loop ran on past --max-captures while it held captures"
    assert src.events.qsize() == 17 and acq.counts["held"] == 0
    assert [o.status for o in outs] == ["spilled"] * 3 and acq.counts["spilled"] == 3

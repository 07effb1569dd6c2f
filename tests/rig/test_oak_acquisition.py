"""A rig of four OAK sockets on one device, watching the line, through a disconnect and back (depthai fake)."""

from __future__ import annotations

import threading
import time

from rig.acquisition import Acquisition, Thresholds, open_cameras
from rig.camera import CameraSettings
from rig.oak import OakCamera
from rig.store import CaptureStore
from rig.triggers import SoftwareTrigger
from tests.rig.conftest import assert_store_sound
from tests.rig.fake_depthai import FakeDai, Hardware, Sensor


def test_disconnect_mid_watch_refuses_whole_then_the_rig_resumes(store_root):
    hw = Hardware("14442C10D13EABCE00", "RVC2", [Sensor(f"CAM_{c}", "OV9782", 1280, 800) for c in "ABCD"], fail_after=4 * 6)
    dai = FakeDai(hw)
    cams = [
        OakCamera(f"cam{i}", hw.device_id, socket=f"CAM_{s}", dai=dai, device_options={"reopen_s": 1.0, "backoff_s": (0.05, 0.2)})
        for i, s in enumerate("ABCD")
    ]
    open_cameras(cams, CameraSettings(64, 40, exposure_us=4000, iso=200, white_balance_k=5600))
    acq = Acquisition(
        cams,
        CaptureStore(store_root, min_free_bytes=0),
        settings=CameraSettings(64, 40, exposure_us=4000, iso=200, white_balance_k=5600),
        thresholds=Thresholds(sync_tolerance_ns=40_000_000, grab_timeout_s=1.0),
    )
    trig = SoftwareTrigger()
    stop = threading.Event()
    outcomes, alarms = [], []

    def line():  # a part every 60 ms; the cable is pushed back in after 8 refused triggers
        while not stop.is_set():
            trig.fire()
            if not hw.plugged and sum(o.status == "refused" for o in outcomes) >= 8:
                hw.replug()
            time.sleep(0.06)

    plc = threading.Thread(target=line)
    plc.start()
    runner = threading.Thread(
        target=acq.run, args=(trig, stop), kwargs={"on_outcome": lambda o: (outcomes.append(o), alarms.append(acq.camera_alarm))}
    )
    runner.start()
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and not (
        hw.plugged
        and hw.holder is not None
        and sum(o.status == "committed" for o in outcomes[-3:]) == 3
        and any(o.status == "refused" for o in outcomes)
    ):
        time.sleep(0.05)
    stop.set()
    runner.join()
    plc.join()
    device = cams[0]._device
    acq.close()

    statuses = [o.status for o in outcomes]
    first_refused = statuses.index("refused")
    assert set(statuses[:first_refused]) == {"committed"}
    refused = [o for o in outcomes if o.status == "refused"]
    assert len(refused) >= 8 and acq.counts["refused"] == len(refused) and "quarantined" not in statuses
    # the in-flight capture names the cameras and is refused whole; the following ones are refused before grabbing
    assert refused[0].reason.startswith(
        "cameras cam0, cam1, cam2, cam3 are down: OAK 14442C10D13EABCE00 is disconnected (X_LINK_ERROR); reconnecting"
    )
    assert refused[0].reason.endswith("the capture in flight was refused whole") and refused[-1].reason.endswith("no capture taken")
    assert all(o.capture_id == "" for o in refused)
    # the rig resumed by itself, and the store holds only whole captures (0 half-stored)
    assert statuses[-3:] == ["committed"] * 3 and alarms[-1] == ""
    committed = [o.capture_id for o in outcomes if o.status == "committed"]
    stored = assert_store_sound(store_root, committed)
    assert stored == sorted(committed) and acq.store.quarantined_ids() == []
    for cid in stored:
        meta = acq.store.read(cid).meta
        assert len(acq.store.read(cid).frames) == 4 and set(meta["trigger_to_exposure_ns"]) == {"cam0", "cam1", "cam2", "cam3"}
        assert all(0 < v < 500_000_000 for v in meta["trigger_to_exposure_ns"].values()) and meta["sync_spread_ns"] < 40_000_000
    assert device.reconnects == 1 and all(d.isClosed() for d in dai.opened)

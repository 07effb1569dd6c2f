"""The OAK driver and its device manager against tests/rig/fake_depthai.py (depthai's documented behaviour, no device)."""

from __future__ import annotations

import datetime as dt
import time

import numpy as np
import pytest

from deploy.kiosk_state import CameraStatus, drift_alarm
from rig.camera import CameraError, CameraSettings
from rig.oak import OakCamera, describe_oak_device, factory_camera, list_oak_devices, opencv_distortion
from rig.oak_devices import refuse_sync
from tests.rig.fake_depthai import CalibrationHandler, FakeDai, Hardware, Sensor

LOCKED = dict(exposure_us=5000, iso=200, white_balance_k=5600)
FAST = {"reopen_s": 1.0, "backoff_s": (0.02, 0.1)}


def ffc_4p(device_id="18443010D1C2A41200", **kw) -> Hardware:
    """An OAK-FFC-4P with four global-shutter OV9282 modules."""
    return Hardware(device_id, "RVC2", [Sensor(f"CAM_{c}", "OV9282", 1280, 800) for c in "ABCD"], **kw)


def oak_d(device_id="19443010D1C2A41200") -> Hardware:
    """RGB IMX378 (4056x3040, streams a 16:9 window) and two OV9282."""
    return Hardware(
        device_id,
        "RVC2",
        [
            Sensor("CAM_A", "IMX378", 4056, 3040, window=(108, 440, 3840, 2160)),
            Sensor("CAM_B", "OV9282", 1280, 800),
            Sensor("CAM_C", "OV9282", 1280, 800),
        ],
        product="OAK-D",
    )


def cam(dai, camera_id="cam0", device_id="18443010D1C2A41200", **kw) -> OakCamera:
    kw.setdefault("converge_s", 0.05)
    return OakCamera(camera_id, device_id, dai=dai, device_options=FAST, **kw)


def wait(cond, timeout=5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.01)
    return False


def test_lists_and_describes_devices():
    dai = FakeDai(ffc_4p(), Hardware("OAK4", "RVC4", [Sensor("CAM_A", "IMX586", 4000, 3000)], product="OAK4-D"))
    assert [(d["device_id"], d["platform"], d["state"]) for d in list_oak_devices(dai)] == [
        ("18443010D1C2A41200", "RVC2", "X_LINK_UNBOOTED"),
        ("OAK4", "RVC4", "X_LINK_UNBOOTED"),
    ]
    d = describe_oak_device("18443010D1C2A41200", dai)
    assert d["product"] == "OAK-FFC-4P" and [s["socket"] for s in d["sockets"]] == ["CAM_A", "CAM_B", "CAM_C", "CAM_D"]
    assert d["sockets"][0]["sensor"] == "OV9282" and d["sockets"][0]["sync"] == ["software", "fsin (snapshot on FSIN edge)"]
    assert describe_oak_device("OAK4", dai)["sockets"][0]["sync"] == ["software", "fsin (continuous FSYNC, device slave)"]
    assert all(dev.isClosed() for dev in dai.opened)  # listing leaves the devices free


def test_distortion_and_factory_intrinsics():
    assert opencv_distortion([0.0] * 14).size == 0
    np.testing.assert_array_equal(opencv_distortion([-0.1, 0.02, 0.001, -0.001] + [0.0] * 10), [-0.1, 0.02, 0.001, -0.001])
    assert opencv_distortion([0, 0, 0, 0, 0, 0.1] + [0.0] * 8).size == 8
    with pytest.raises(CameraError, match="tilt"):
        opencv_distortion([0.0] * 12 + [0.01, 0.0])
    hw = ffc_4p()
    c = factory_camera(CalibrationHandler(hw), FakeDai.CameraBoardSocket.CAM_A, 128, 80)
    # OpenCV's principal point (pixel centres at integers) moves by +0.5 to ours
    np.testing.assert_allclose(c.K[:2, 2], [(639.5 + 0.5) * 0.1, (399.5 + 0.5) * 0.1])
    assert c.dist.size == 4


def test_auto_converges_once_then_locks_and_grabs_rgb():
    dai = FakeDai(ffc_4p())
    c = cam(dai)
    c.open()
    s = c.configure(CameraSettings(64, 40))
    assert s.exposure_us is not None and s.exposure_us < 20000 and (s.iso, s.white_balance_k, s.focus) == (400, 4800, 120)
    node = dai.pipelines[-1].nodes[0]
    assert node.runtime["setManualExposure"] == (s.exposure_us, 400) and node.runtime["setManualWhiteBalance"] == (4800,)
    c.arm(1)
    t_arm = time.monotonic_ns()
    f = c.grab(1.0)
    assert f.timestamp_ns >= t_arm - 1_000_000 and f.image.shape == (40, 64, 3)
    assert tuple(f.image[0, 0]) == (50, 90, 200)  # BGR from the device, RGB in the frame
    assert f.settings["exposure_start_ns"] == f.timestamp_ns == f.settings["readout_ns"] - f.settings["exposure_us"] * 1000
    assert c.health().ok and "OV9282 (RVC2)" in c.health().detail
    c.close()
    assert all(d.isClosed() for d in dai.opened) and not dai.pipelines[-1].isRunning()


def test_reconfigure_twice_reopens_the_device_stop_closed():
    dai = FakeDai(ffc_4p())
    c = cam(dai)
    c.open()
    for size in [(64, 40), (128, 80), (96, 60)]:
        c.configure(CameraSettings(*size, **LOCKED))
        c.arm(0)
        assert c.grab(1.0).image.shape == (size[1], size[0], 3) and c.camera.width == size[0]
    # every rebuild followed Pipeline.stop() (which closed the device) with a fresh Device
    assert len(dai.pipelines) == 3 and len(dai.opened) == 3
    assert [p.isRunning() for p in dai.pipelines] == [False, False, True] and [d.isClosed() for d in dai.opened] == [True, True, False]
    # a photometric change goes to the running pipeline, no rebuild
    c.configure(CameraSettings(96, 60, exposure_us=7000, iso=200, white_balance_k=5600))
    assert len(dai.pipelines) == 3 and dai.pipelines[-1].nodes[0].runtime["setManualExposure"] == (7000, 200)
    c.close()


def test_four_sockets_share_one_device_and_one_pipeline():
    dai = FakeDai(ffc_4p())
    cams = [cam(dai, f"cam{i}", socket=f"CAM_{s}") for i, s in enumerate("ABCD")]
    for c in cams:
        c.open()
    for c in cams:
        c.configure(CameraSettings(64, 40, **LOCKED))
    assert len(dai.opened) == 1 and len(dai.pipelines) == 1  # sockets opened together build once
    assert sorted(n.socket.name for n in dai.pipelines[-1].nodes) == ["CAM_A", "CAM_B", "CAM_C", "CAM_D"]
    for c in cams:
        c.arm(1)
    frames = [c.grab(1.0) for c in cams]
    assert [f.settings["socket"] for f in frames] == ["CAM_A", "CAM_B", "CAM_C", "CAM_D"]
    assert max(f.timestamp_ns for f in frames) - min(f.timestamp_ns for f in frames) < 40_000_000
    with pytest.raises(CameraError) as e:
        cam(dai, "cam9", socket="CAM_B").open()
    assert str(e.value) == "cam9: CAM_B of OAK 18443010D1C2A41200 is already camera cam1; one camera per socket"
    for c in cams[:3]:
        c.close()
    assert not dai.opened[0].isClosed()  # the last socket still holds the device
    cams[3].close()
    assert dai.opened[0].isClosed()


def test_refusals_are_one_sentence_each():
    dai = FakeDai(
        ffc_4p(),
        oak_d(),
        Hardware("OAK4", "RVC4", [Sensor("CAM_A", "IMX586", 4000, 3000)], sync_role_error="no FSYNC signal on the M8 input"),
    )

    def refusal(fn) -> str:
        with pytest.raises(CameraError) as e:
            fn()
        return str(e.value)

    assert refusal(lambda: cam(dai, device_id="NOPE").open()).startswith("cam0: OAK NOPE not found or busy (No available devices")
    assert refusal(lambda: cam(dai, socket="CAM_Z").open()) == "cam0: unknown camera socket 'CAM_Z' (use CAM_A, CAM_B, ...)"
    assert refusal(lambda: cam(dai, device_id="19443010D1C2A41200", socket="CAM_D").open()) == (
        "cam0: OAK 19443010D1C2A41200 has no camera on CAM_D (connected: CAM_A (IMX378), CAM_B (OV9282), CAM_C (OV9282))"
    )
    rgb = cam(dai, "rgb", device_id="19443010D1C2A41200", socket="CAM_A")
    rgb.open()
    assert refusal(lambda: rgb.configure(CameraSettings(64, 36, sync="fsin", **LOCKED))) == (
        "rgb: CAM_A is a rolling-shutter IMX378: snapshot sync is not supported (only OV9282, OV9782, AR0234), use sync = 'software'"
    )
    assert refusal(lambda: rgb.configure(CameraSettings(64, 36, sync="fsin"))).startswith(
        "rgb: sync 'fsin' needs fixed exposure_us, iso and white_balance_k"
    )
    rgb.close()
    four = cam(dai, "four", device_id="OAK4")
    four.open()
    assert refusal(lambda: four.configure(CameraSettings(64, 48, sync="fsin", **LOCKED))) == (
        "four: OAK OAK4 refused the external frame-sync role SLAVE (no FSYNC signal on the M8 input); check the M8 sync cable, or use sync = 'software'"
    )
    four.close()
    other_process = dai.Device(dai.DeviceInfo("18443010D1C2A41200"))
    assert "X_LINK_DEVICE_ALREADY_IN_USE" in refusal(lambda: cam(dai).open())
    other_process.close()


def test_rvc4_fsin_takes_the_slave_role():
    dai = FakeDai(Hardware("OAK4", "RVC4", [Sensor("CAM_A", "IMX586", 4000, 3000)]))
    c = cam(dai, device_id="OAK4")
    c.open()
    c.configure(CameraSettings(64, 48, sync="fsin", **LOCKED))
    assert dai.opened[-1].getExternalFrameSyncRole() is dai.ExternalFrameSyncRole.SLAVE
    assert "setExternalTrigger" not in dai.pipelines[-1].nodes[0].initialControl.values  # RVC2's snapshot call is not made
    c.arm(1)
    assert c.grab(1.0).settings["sync"] == "fsin"
    c.close()


def test_rvc2_snapshot_one_frame_per_fsin_edge():
    hw = ffc_4p()
    dai = FakeDai(hw)
    c = cam(dai, fsin_discard=2)
    c.open()
    c.configure(CameraSettings(64, 40, sync="fsin", **LOCKED))
    ctrl = dai.pipelines[-1].nodes[0].initialControl.values
    assert ctrl["setExternalTrigger"] == (3, 2) and ctrl["setFrameSyncMode"] == (dai.CameraControl.FrameSyncMode.INPUT,)
    c.arm(1)
    with pytest.raises(CameraError, match="no frame from OAK"):
        c.grab(0.1)  # no edge, no frame
    edge = time.monotonic_ns()
    hw.fsin(edge)
    time.sleep(0.02)  # the trigger message reaches the host after the edge
    c.arm(2)
    f = c.grab(1.0)
    assert (
        abs(f.timestamp_ns - edge - (40_000 + 2 * 33_333_333)) < 1000
    )  # (depthai times are µs timedeltas); the burst's first two (degraded) frames were discarded
    c.close()


def test_a_frame_straddling_the_trigger_is_discarded():
    dai = FakeDai(ffc_4p())
    c = cam(dai)
    c.open()
    c.configure(CameraSettings(64, 40, exposure_us=20000, iso=200, white_balance_k=5600))
    c.arm(1)
    armed = c._armed_ns
    q = dai.pipelines[-1].queues[0]
    q.t0 = armed - 5_000_000 - q.next_frame * (1_000_000_000 // 30)  # the next frame's exposure began 5 ms before the trigger
    f = c.grab(1.0)
    assert c.straddling == 1 and f.settings["straddling_discarded"] == 1
    assert f.timestamp_ns >= armed and abs(f.timestamp_ns - armed - (1_000_000_000 // 30 - 5_000_000)) < 1000
    c.close()


def test_intrinsics_come_from_the_cropped_output_and_a_mismatch_is_a_warning():
    dai = FakeDai(oak_d())
    c = cam(dai, device_id="19443010D1C2A41200")
    c.open()
    c.configure(CameraSettings(640, 360, **LOCKED))
    tr = dai.pipelines[-1].queues[0].get(dt.timedelta(seconds=1)).getTransformation()
    np.testing.assert_allclose(c.camera.K, np.array(tr.getIntrinsicMatrix()) + [[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
    full = np.array(dai.opened[-1].readCalibration().getCameraIntrinsics(dai.CameraBoardSocket.CAM_A, 640, 360))
    assert (
        c.camera.K[0, 0] == pytest.approx(0.8 * 4056 * 640 / 3840) and abs(full[0, 0] - c.camera.K[0, 0]) > 25
    )  # the scaled calibration is 5% off
    assert c.camera.dist.size == 4 and c.calibration_warning == ""
    c.close()
    # a rig calibration made from the factory intrinsics scaled to 640x360 does not match what is delivered
    calibrated = factory_camera(CalibrationHandler(oak_d()), dai.CameraBoardSocket.CAM_A, 640, 360)
    c = cam(dai, device_id="19443010D1C2A41200", camera=calibrated)
    c.open()
    c.configure(CameraSettings(640, 360, **LOCKED))
    c.arm(1)
    f = c.grab(1.0)
    assert (
        c.calibration_warning.startswith("the delivered 640x360 frames have fx 540.8")
        and "recalibrate at this output size" in c.calibration_warning
    )
    assert f.settings["calibration_warning"] == c.calibration_warning and "calibration warning" in c.health().detail
    assert c.camera.K[0, 0] == calibrated.K[0, 0]  # the rig calibration stays in force; the warning says it disagrees
    c.close()


def test_disconnect_then_background_reconnect_with_the_same_settings():
    hw = ffc_4p(fail_after=10)
    dai = FakeDai(hw)
    c = cam(dai)
    c.open()
    c.configure(CameraSettings(64, 40, exposure_us=6000, iso=300, white_balance_k=5000))
    with pytest.raises(CameraError) as e:
        for seq in range(20):
            c.arm(seq)
            c.grab(1.0)
    assert str(e.value).startswith("cam0: OAK 18443010D1C2A41200 is disconnected (X_LINK_ERROR); reconnecting in the background")
    h = c.health()
    assert c.reconnecting and not h.ok and "reconnecting" in h.detail
    # what the kiosk shows for it
    text = drift_alarm(CameraStatus("cam0", h.ok, detail=h.detail)).text
    assert text.startswith(
        "Camera cam0 is not answering (OAK 18443010D1C2A41200 is disconnected (X_LINK_ERROR); reconnecting in the background"
    )
    assert text.endswith(") — captures are refused until it is back; check its cable and power.")
    with pytest.raises(CameraError, match="is disconnected"):
        c.arm(21)
    time.sleep(0.3)
    assert c.reconnecting and c._device.attempts >= 2  # still away: attempts go on with back-off
    hw.replug()
    assert wait(lambda: not c.reconnecting and c.health().ok)
    c.arm(22)
    f = c.grab(1.0)
    assert (f.settings["exposure_us"], f.settings["iso"], f.settings["white_balance_k"]) == (6000, 300, 5000)
    assert c._device.reconnects == 1 and dai.opened[-1].isClosed() is False
    c.close()


def test_an_idle_device_that_drops_is_noticed_by_its_health_check():
    hw = ffc_4p()
    dai = FakeDai(hw)
    c = cam(dai)
    c.open()
    c.configure(CameraSettings(64, 40, **LOCKED))
    hw.unplug()
    assert not c.health().ok and c.reconnecting
    hw.replug()
    assert wait(lambda: c.health().ok)
    c.close()


def test_sync_refusals_per_platform_and_sensor():
    assert refuse_sync("RVC2", "CAM_A", "OV9282") == "" and refuse_sync("RVC4", "CAM_A", "IMX586") == ""
    assert refuse_sync("RVC2", "CAM_C", "IMX296") == (
        "CAM_C is a global-shutter IMX296: snapshot sync is not supported (only OV9282, OV9782, AR0234), use sync = 'software'"
    )
    assert (
        refuse_sync("RVC2", "CAM_D", "S5K33D")
        == "CAM_D is a S5K33D: snapshot sync is not supported (only OV9282, OV9782, AR0234), use sync = 'software'"
    )
    assert refuse_sync("RVC3", "CAM_A", "OV9282") == "CAM_A: hardware frame sync is not supported on RVC3 devices, use sync = 'software'"


def test_mixed_sync_on_one_device_builds_once():
    """OAK-D: the mono pair in snapshot sync, the rolling-shutter RGB streaming (software), one pipeline."""
    dai = FakeDai(oak_d())
    rgb, left, right = (
        cam(dai, n, device_id="19443010D1C2A41200", socket=s) for n, s in (("rgb", "CAM_A"), ("left", "CAM_B"), ("right", "CAM_C"))
    )
    for c in (rgb, left, right):
        c.open()
    for c in (left, right):
        c.configure(CameraSettings(64, 40, sync="fsin", **LOCKED))
    rgb.configure(CameraSettings(64, 40, **LOCKED))
    assert len(dai.pipelines) == 1
    nodes = {n.socket.name: n.initialControl.values for n in dai.pipelines[-1].nodes}
    assert "setExternalTrigger" in nodes["CAM_B"] and "setExternalTrigger" in nodes["CAM_C"] and "setExternalTrigger" not in nodes["CAM_A"]
    for c in (rgb, left, right):
        c.close()

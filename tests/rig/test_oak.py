"""The OAK driver against a fake of the few depthai objects it touches (no device, no real Pipeline)."""

from __future__ import annotations

import datetime as dt
import time
from types import SimpleNamespace

import numpy as np
import pytest

from rig.camera import CameraError, CameraSettings
from rig.oak import OakCamera, factory_camera, list_oak_devices, opencv_distortion


class FakeControl:
    def __init__(self):
        self.calls = []

    def __getattr__(self, name):
        if name.startswith("set"):
            return lambda *a: self.calls.append((name, *a)) or self
        raise AttributeError(name)


class FakeFrame:
    def __init__(self, ts_ns, seq, exposure_us, iso, wb, lens=120):
        self.ts_ns, self.seq, self.exposure_us, self.iso, self.wb, self.lens = ts_ns, seq, exposure_us, iso, wb, lens

    def getTimestamp(self):
        return dt.timedelta(microseconds=self.ts_ns // 1000)

    def getCvFrame(self):
        img = np.zeros((48, 64, 3), np.uint8)
        img[..., 0] = 200  # BGR: blue channel
        img[..., 2] = 50
        return img

    def getExposureTime(self):
        return dt.timedelta(microseconds=self.exposure_us)

    getSensitivity = lambda self: self.iso  # noqa: E731
    getColorTemperature = lambda self: self.wb  # noqa: E731
    getLensPosition = lambda self: self.lens  # noqa: E731
    getSequenceNum = lambda self: self.seq  # noqa: E731


class FakeQueue:
    """Frames at 30 fps on the host monotonic clock; auto exposure drifts until locked."""

    def __init__(self, device):
        self.device, self.seq, self.exposure = device, 0, 20000

    def get(self, timeout):
        if self.device.unplugged:
            raise RuntimeError("Communication exception - possible device error/misconfiguration")
        time.sleep(1 / 300)
        self.seq += 1
        self.exposure = max(8000, self.exposure - 1000)
        return FakeFrame(time.monotonic_ns(), self.seq, self.exposure, 400, 4800)

    def tryGetAll(self):
        if self.device.unplugged:
            raise RuntimeError("device gone")
        return []


class FakeCameraNode:
    def __init__(self, device):
        self.initialControl = FakeControl()
        self.device = device
        self.sent = []
        self.inputControl = SimpleNamespace(createInputQueue=lambda: SimpleNamespace(send=self.sent.append))

    def build(self, socket):
        self.socket = socket
        return self

    def requestOutput(self, size, type):
        self.size, self.type = size, type
        return SimpleNamespace(createOutputQueue=lambda maxSize, blocking: FakeQueue(self.device))


class FakeCalibration:
    def getCameraIntrinsics(self, socket, w, h):
        return [[500.0 * w / 640, 0, 319.5 * w / 640], [0, 500.0 * h / 480, 239.5 * h / 480], [0, 0, 1]]

    def getDistortionCoefficients(self, socket):
        return [-0.1, 0.02, 0.001, -0.001, 0.0] + [0.0] * 9


def fake_dai(available=("18443010D1C2A41200",)):
    state = SimpleNamespace(devices={}, pipelines=[])

    class Device:
        def __init__(self, info):
            if info.id not in available:
                raise RuntimeError(f"No available devices ({info.id})")
            self.id, self.unplugged, self.closed, self.role = info.id, False, False, None
            state.devices[info.id] = self

        @staticmethod
        def getAllAvailableDevices():
            return [SimpleNamespace(getDeviceId=lambda d=d: d, name="1.1", state=SimpleNamespace(name="X_LINK_UNBOOTED")) for d in available]

        def readCalibration(self):
            return FakeCalibration()

        def isClosed(self):
            return self.closed or self.unplugged

        def close(self):
            self.closed = True

        def setExternalFrameSyncRole(self, role):
            self.role = role
            return True, ""

        def getChipTemperature(self):
            return SimpleNamespace(average=41.0)

    class Pipeline:
        def __init__(self, device):
            self.device, self.started, self.node = device, False, None
            state.pipelines.append(self)

        def create(self, kind):
            self.node = FakeCameraNode(self.device)
            return self.node

        def start(self):
            self.started = True

        def stop(self):
            self.started = False

    dai = SimpleNamespace(
        Device=Device,
        DeviceInfo=lambda device_id: SimpleNamespace(id=device_id),
        Pipeline=Pipeline,
        node=SimpleNamespace(Camera="Camera"),
        CameraBoardSocket=SimpleNamespace(CAM_A="CAM_A", CAM_B="CAM_B"),
        CameraControl=FakeControl,
        ImgFrame=SimpleNamespace(Type=SimpleNamespace(BGR888i="BGR888i")),
        ExternalFrameSyncRole=SimpleNamespace(SLAVE="SLAVE"),
        MessageQueue=SimpleNamespace(QueueException=type("QueueException", (Exception,), {})),
    )
    return dai, state


def test_lists_devices():
    dai, _ = fake_dai()
    assert list_oak_devices(dai) == [{"device_id": "18443010D1C2A41200", "name": "1.1", "state": "X_LINK_UNBOOTED"}]


def test_distortion_and_factory_intrinsics():
    assert opencv_distortion([0.0] * 14).size == 0
    np.testing.assert_array_equal(opencv_distortion([-0.1, 0.02, 0.001, -0.001] + [0.0] * 10), [-0.1, 0.02, 0.001, -0.001])
    assert opencv_distortion([0, 0, 0, 0, 0, 0.1] + [0.0] * 8).size == 8
    with pytest.raises(CameraError, match="tilt"):
        opencv_distortion([0.0] * 12 + [0.01, 0.0])
    cam = factory_camera(FakeCalibration(), "CAM_A", 64, 48)
    # OpenCV's principal point (pixel centres at integers) moves by +0.5 to ours
    np.testing.assert_allclose(cam.K[:2, 2], [319.5 * 0.1 + 0.5, 239.5 * 0.1 + 0.5])
    assert cam.dist.size == 4


def test_auto_converges_once_then_locks_and_grabs_rgb():
    dai, state = fake_dai()
    cam = OakCamera("cam0", "18443010D1C2A41200", dai=dai, converge_s=0.05)
    cam.open()
    s = cam.configure(CameraSettings(64, 48))
    node = state.pipelines[-1].node
    assert state.pipelines[-1].started and node.size == (64, 48) and node.type == "BGR888i"
    assert s.exposure_us is not None and s.exposure_us < 20000 and (s.iso, s.white_balance_k, s.focus) == (400, 4800, 120)
    lock = node.sent[-1].calls
    assert ("setManualExposure", s.exposure_us, 400) in lock and ("setManualWhiteBalance", 4800) in lock and ("setManualFocus", 120) in lock
    cam.arm(1)
    t_arm = time.monotonic_ns()
    f = cam.grab(1.0)
    assert f.timestamp_ns >= t_arm - 1_000_000 and f.image.shape == (48, 64, 3)
    assert tuple(f.image[0, 0]) == (50, 0, 200)  # BGR from the device, RGB in the frame
    assert f.settings["device_id"] == "18443010D1C2A41200" and cam.health().ok
    assert cam.camera.width == 64 and cam.camera.dist.size == 4
    cam.close()
    assert state.devices["18443010D1C2A41200"].closed and not state.pipelines[-1].started


def test_fixed_settings_and_fsin_go_into_the_initial_control():
    dai, state = fake_dai()
    cam = OakCamera("cam0", "18443010D1C2A41200", dai=dai)
    cam.open()
    s = cam.configure(CameraSettings(64, 48, exposure_us=5000, iso=200, white_balance_k=5600, focus=90, sync="fsin"))
    calls = state.pipelines[-1].node.initialControl.calls
    assert ("setExternalTrigger", 1, 0) in calls and ("setManualExposure", 5000, 200) in calls
    assert ("setManualWhiteBalance", 5600) in calls and ("setManualFocus", 90) in calls
    assert state.devices["18443010D1C2A41200"].role == "SLAVE" and s.exposure_us == 5000
    with pytest.raises(CameraError, match="fsin' needs fixed exposure"):
        cam.configure(CameraSettings(64, 48, sync="fsin"))


def test_missing_and_unplugged_devices_raise_camera_errors():
    dai, state = fake_dai()
    with pytest.raises(CameraError, match="not found or busy"):
        OakCamera("cam9", "NOPE", dai=dai).open()
    cam = OakCamera("cam0", "18443010D1C2A41200", dai=dai, converge_s=0.01)
    cam.open()
    cam.configure(CameraSettings(64, 48, exposure_us=5000, iso=200, white_balance_k=5600))
    state.devices["18443010D1C2A41200"].unplugged = True
    with pytest.raises(CameraError, match="disconnected"):
        cam.arm(2)
    assert not cam.health().ok

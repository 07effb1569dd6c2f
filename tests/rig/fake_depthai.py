"""A fake of the depthai v3 API surface the OAK driver uses, written from depthai's documentation and
depthai-core's source (not from the driver), so the driver's tests meet depthai's behaviour:

- `Pipeline.stop()` closes the pipeline's default device (depthai-core `PipelineImpl::stop`), and
  its output queues: a later `get` raises `MessageQueue.QueueException`; a stopped pipeline's
  device cannot carry a new pipeline.
- A device can be opened once: a second `Device(...)` on it raises; `getAllAvailableDevices()`
  lists only devices nobody holds.
- `ImgFrame.getTimestamp()` is the end of exposure (readout start); `getTimestamp(offset)`
  subtracts the exposure time (START) or half of it (MIDDLE), as `ImgFrame::getTimestamp` does.
- `ImgFrame.getTransformation()` carries the intrinsics of the delivered output: the sensor mode's
  window of the calibrated resolution, then the requested size by `ImgResizeMode` (CROP default).
  `CalibrationHandler.getCameraIntrinsics(socket, w, h)` scales from the calibrated full resolution
  (keepAspectRatio: scale to cover, centre-crop the rest), as documented.
- Snapshot mode (`CameraControl.setExternalTrigger`) works on RVC2 with the sensors the frame-sync
  docs list (OV9282, OV9782, AR0234): one burst per FSIN edge, the first `numFramesDiscard`
  dropped. Other sensors ignore it and free-run (the IMX296 report, depthai-core #895).
- RVC4 devices take `Device.setExternalFrameSyncRole` (SLAVE: "must lock onto an external frame sync
  signal"); on RVC2 it is refused (an assumption: depthai documents the role for RVC4 devices only).
- `Hardware.fail_after` frames: the link drops with X_LINK_ERROR, the device is gone until `replug()`.

`FakeDai(hardware...)` is used in place of the `depthai` module.
"""

from __future__ import annotations

import datetime as dt
import enum
import threading
import time
from dataclasses import dataclass, field

import numpy as np

SNAPSHOT_SENSORS = ("OV9282", "OV9782", "AR0234")
XLINK_ERROR = "Communication exception - possible device error/misconfiguration. Original message 'Couldn't read data from stream: '__x_0_1' (X_LINK_ERROR)'"


class CameraBoardSocket(enum.Enum):
    AUTO = -1
    CAM_A = 0
    CAM_B = 1
    CAM_C = 2
    CAM_D = 3
    CAM_E = 4


Platform = enum.Enum("Platform", "RVC2 RVC3 RVC4")
ExternalFrameSyncRole = enum.Enum("ExternalFrameSyncRole", "AUTO_DETECT MASTER SLAVE")
CameraExposureOffset = enum.Enum("CameraExposureOffset", "START MIDDLE END")
ImgResizeMode = enum.Enum("ImgResizeMode", "CROP STRETCH LETTERBOX")
XLinkDeviceState = enum.Enum("XLinkDeviceState", "X_LINK_UNBOOTED X_LINK_BOOTED X_LINK_BOOTLOADER")
XLinkPlatform = enum.Enum("XLinkPlatform", "X_LINK_ANY_PLATFORM X_LINK_MYRIAD_2 X_LINK_MYRIAD_X X_LINK_RVC3 X_LINK_RVC4")
_XLINK = {"RVC2": XLinkPlatform.X_LINK_MYRIAD_X, "RVC3": XLinkPlatform.X_LINK_RVC3, "RVC4": XLinkPlatform.X_LINK_RVC4}


@dataclass
class Sensor:
    """One camera module on a socket. `window`: the part of the calibrated resolution the streaming
    sensor mode reads (x0, y0, w, h), e.g. a 16:9 mode of a 4:3 sensor."""

    socket: str
    name: str
    width: int
    height: int
    window: tuple[int, int, int, int] | None = None
    fx: float = 0.0

    def __post_init__(self):
        self.window = self.window or (0, 0, self.width, self.height)
        self.fx = self.fx or 0.8 * self.width


@dataclass
class Hardware:
    """A physical OAK on the bus."""

    device_id: str
    platform: str = "RVC2"
    sensors: list[Sensor] = field(default_factory=list)
    product: str = "OAK-FFC-4P"
    fail_after: int | None = None  # frames delivered before the link drops (X_LINK_ERROR)
    sync_role_error: str = ""  # RVC4: why setExternalFrameSyncRole fails (e.g. nothing on the M8 sync input)
    plugged: bool = True
    holder: object = None
    frames: int = 0
    edges: list[int] = field(default_factory=list)  # FSIN edge times (host monotonic ns)

    def sensor(self, socket: str) -> Sensor | None:
        return next((s for s in self.sensors if s.socket == socket), None)

    def unplug(self) -> None:
        self.plugged = False
        if self.holder is not None:
            self.holder._lost = True

    def replug(self) -> None:
        self.plugged, self.frames = True, 0
        self.fail_after = None

    def fsin(self, t_ns: int | None = None) -> None:
        """A rising edge on the FSIN line (the photo-eye), at host time `t_ns` (now)."""
        self.edges.append(time.monotonic_ns() if t_ns is None else t_ns)


class QueueException(RuntimeError):
    pass


class CameraControl:
    FrameSyncMode = enum.Enum("FrameSyncMode", "OFF OUTPUT INPUT")

    def __init__(self):
        self.calls: list[tuple] = []
        self.values: dict[str, tuple] = {}

    def _set(self, name, *args):
        self.calls.append((name, *args))
        self.values[name] = args
        return self

    def setManualExposure(self, exposure_us: int, iso: int):
        return self._set("setManualExposure", exposure_us, iso)

    def setManualWhiteBalance(self, kelvin: int):
        return self._set("setManualWhiteBalance", kelvin)

    def setManualFocus(self, position: int):
        return self._set("setManualFocus", position)

    def setExternalTrigger(self, numFramesBurst: int, numFramesDiscard: int):
        return self._set("setExternalTrigger", numFramesBurst, numFramesDiscard)

    def setFrameSyncMode(self, mode):
        return self._set("setFrameSyncMode", mode)


class ImgTransformation:
    def __init__(self, k: np.ndarray, size: tuple[int, int], source_k: np.ndarray, source_size: tuple[int, int], dist: list[float]):
        self._k, self._size, self._sk, self._ss, self._dist = k, size, source_k, source_size, dist

    def getIntrinsicMatrix(self):
        return self._k.tolist()

    def getSourceIntrinsicMatrix(self):
        return self._sk.tolist()

    def getSize(self):
        return self._size

    def getSourceSize(self):
        return self._ss

    def getDistortionCoefficients(self):
        return list(self._dist)


class ImgFrame:
    Type = enum.Enum("Type", "BGR888i BGR888p NV12 GRAY8")

    def __init__(self, image, readout_ns, exposure_us, iso, wb, lens, seq, transformation, socket):
        self._image, self._ts, self._exp, self._iso, self._wb, self._lens = image, readout_ns, exposure_us, iso, wb, lens
        self._seq, self._tr, self._socket = seq, transformation, socket

    def getTimestamp(self, offset=None) -> dt.timedelta:
        ns = self._ts
        if offset is CameraExposureOffset.START:
            ns -= self._exp * 1000
        elif offset is CameraExposureOffset.MIDDLE:
            ns -= self._exp * 500
        return dt.timedelta(microseconds=ns / 1000)

    def getExposureTime(self) -> dt.timedelta:
        return dt.timedelta(microseconds=self._exp)

    def getCvFrame(self):
        return self._image

    def getWidth(self):
        return self._image.shape[1]

    def getHeight(self):
        return self._image.shape[0]

    def getTransformation(self):
        return self._tr

    def getInstanceNum(self):
        return self._socket.value

    getSensitivity = lambda self: self._iso  # noqa: E731
    getColorTemperature = lambda self: self._wb  # noqa: E731
    getLensPosition = lambda self: self._lens  # noqa: E731
    getSequenceNum = lambda self: self._seq  # noqa: E731


def _intrinsics(sensor: Sensor) -> np.ndarray:
    return np.array([[sensor.fx, 0, sensor.width / 2 - 0.5], [0, sensor.fx, sensor.height / 2 - 0.5], [0, 0, 1]])


def _scale_crop(k: np.ndarray, src: tuple[int, int], dst: tuple[int, int], mode) -> np.ndarray:
    """Intrinsics after resizing a `src` (w, h) image to `dst` by depthai's resize modes (pixel centres at integers)."""
    (sw, sh), (dw, dh) = src, dst
    k = k.copy()
    if mode is ImgResizeMode.STRETCH:
        sx, sy, ox, oy = dw / sw, dh / sh, 0.0, 0.0
    else:
        s = max(dw / sw, dh / sh) if mode is ImgResizeMode.CROP else min(dw / sw, dh / sh)
        sx = sy = s
        ox, oy = (sw * s - dw) / 2, (sh * s - dh) / 2
    k[0, 0] *= sx
    k[1, 1] *= sy
    k[0, 2] = (k[0, 2] + 0.5) * sx - 0.5 - ox
    k[1, 2] = (k[1, 2] + 0.5) * sy - 0.5 - oy
    return k


class CalibrationHandler:
    DIST = [-0.1, 0.02, 0.001, -0.001, 0.0] + [0.0] * 9

    def __init__(self, hw: Hardware):
        self._hw = hw

    def getCameraIntrinsics(self, cameraId, resizeWidth=-1, resizeHeight=-1, keepAspectRatio=True):
        s = self._hw.sensor(cameraId.name)
        if s is None:
            raise RuntimeError(f"There is no Intrinsic matrix available for the the requested cameraID ({cameraId.name})")
        size = (s.width, s.height) if resizeWidth < 0 else (resizeWidth, resizeHeight)
        return _scale_crop(
            _intrinsics(s), (s.width, s.height), size, ImgResizeMode.CROP if keepAspectRatio else ImgResizeMode.STRETCH
        ).tolist()

    def getDistortionCoefficients(self, cameraId):
        return list(self.DIST)


class CameraFeatures:
    def __init__(self, s: Sensor):
        self.socket = getattr(CameraBoardSocket, s.socket)
        self.sensorName, self.width, self.height = s.name, s.width, s.height
        self.supportedTypes = []


class DeviceInfo:
    def __init__(self, hw_or_id, platform=None, state=XLinkDeviceState.X_LINK_UNBOOTED):
        self.deviceId = hw_or_id
        self.name = "1.3"
        self.platform = platform
        self.state = state

    def getDeviceId(self):
        return self.deviceId


class MessageQueue:
    QueueException = QueueException


class _OutputQueue:
    """Frames of one socket: streamed at `fps` on the host clock, or one burst per FSIN edge in snapshot mode."""

    def __init__(self, device: Device, node: _CameraNode, size, resize_mode):
        self.device, self.node, self.size, self.resize_mode = device, node, size, resize_mode
        self.closed = False
        self.seq = 0
        self.t0 = time.monotonic_ns()
        self.next_frame = 0
        self.edge_i = len(device._hw.edges)
        self.pending: list[ImgFrame] = []
        self.auto_exposure = 20000
        self._lock = threading.Lock()

    def _check(self):
        if self.closed:
            raise QueueException("MessageQueue was closed")
        if self.device._lost or not self.device._hw.plugged:
            self.device._lost = True
            raise RuntimeError(XLINK_ERROR)

    def _frame(self, exposure_start_ns: int) -> ImgFrame:
        hw, sensor, ctrl = self.device._hw, self.node.sensor, self.node.control()
        if "setManualExposure" in ctrl:
            exposure_us, iso = ctrl["setManualExposure"]
        else:
            self.auto_exposure = max(8000, self.auto_exposure - 1000)
            exposure_us, iso = self.auto_exposure, 400
        wb = ctrl.get("setManualWhiteBalance", (4800,))[0]
        lens = ctrl.get("setManualFocus", (120,))[0]
        x0, y0, w, h = sensor.window
        k_mode = _intrinsics(sensor)
        k_mode[0, 2] -= x0
        k_mode[1, 2] -= y0
        k = _scale_crop(k_mode, (w, h), self.size, self.resize_mode)
        tr = ImgTransformation(k, self.size, _intrinsics(sensor), (sensor.width, sensor.height), CalibrationHandler.DIST)
        img = np.zeros((self.size[1], self.size[0], 3), np.uint8)
        img[..., 0], img[..., 1], img[..., 2] = 200, 90, 50  # BGR
        self.seq += 1
        hw.frames += 1
        return ImgFrame(img, exposure_start_ns + exposure_us * 1000, exposure_us, iso, wb, lens, self.seq, tr, self.node.socket)

    def _snapshot(self) -> bool:
        hw = self.device._hw
        return "setExternalTrigger" in self.node.control() and hw.platform == "RVC2" and self.node.sensor.name in SNAPSHOT_SENSORS

    def _due(self) -> list[ImgFrame]:
        """Frames whose readout has happened by now."""
        now = time.monotonic_ns()
        out = []
        if self._snapshot():
            burst, discard = self.node.control()["setExternalTrigger"]
            edges = self.device._hw.edges
            exp_ns = self.node.control()["setManualExposure"][0] * 1000 if "setManualExposure" in self.node.control() else 20_000_000
            while self.edge_i < len(edges):
                t = edges[self.edge_i] + 40_000  # sensor latency from the edge to exposure start
                if t + (burst - 1) * 33_333_333 + exp_ns > now:
                    break  # the burst is still being exposed / read out
                frames = [self._frame(t + i * 33_333_333) for i in range(burst)]
                out += frames[discard:]
                self.edge_i += 1
            return out
        period = 1_000_000_000 // 30
        while True:
            start = self.t0 + self.next_frame * period
            exp_us = self.node.control().get("setManualExposure", (self.auto_exposure,))[0]
            if start + exp_us * 1000 > now:
                return out
            out.append(self._frame(start))
            self.next_frame += 1

    def _poll(self) -> ImgFrame | None:
        self._check()
        with self._lock:
            self.pending += self._due()
            if not self.pending:
                return None
            if self.device._hw.fail_after is not None and self.device._hw.frames > self.device._hw.fail_after:
                self.device._hw.unplug()
                self._check()
            return self.pending.pop(0)

    def get(self, timeout: dt.timedelta | None = None):
        deadline = time.monotonic() + (timeout.total_seconds() if timeout is not None else 1e9)
        while True:
            msg = self._poll()
            if msg is not None:
                return msg
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.002)

    def tryGet(self):
        return self._poll()

    def tryGetAll(self):
        out = []
        while (msg := self._poll()) is not None:
            out.append(msg)
        return out


class _InputQueue:
    def __init__(self, node):
        self.node = node

    def send(self, ctrl: CameraControl):
        self.node.runtime.update(ctrl.values)


class _Output:
    def __init__(self, node, size, resize_mode):
        self.node, self.size, self.resize_mode = node, size, resize_mode

    def createOutputQueue(self, maxSize: int = 16, blocking: bool = True):
        q = _OutputQueue(self.node.pipeline.device, self.node, self.size, self.resize_mode)
        self.node.pipeline.queues.append(q)
        return q


class _CameraNode:
    def __init__(self, pipeline):
        self.pipeline = pipeline
        self.initialControl = CameraControl()
        self.runtime: dict[str, tuple] = {}
        self.inputControl = type("Input", (), {"createInputQueue": lambda _self, *a, **k: _InputQueue(self)})()
        self.socket = None
        self.sensor = None
        self.outputs: list[_Output] = []

    def control(self) -> dict:
        return {**self.initialControl.values, **self.runtime}

    def build(self, boardSocket=CameraBoardSocket.AUTO, sensorResolution=None, sensorFps=None):
        dev = self.pipeline.device
        sensor = dev._hw.sensor(boardSocket.name)
        if sensor is None:
            raise RuntimeError(f"Camera on socket {boardSocket.name} is not connected")
        self.socket, self.sensor = boardSocket, sensor
        return self

    def requestOutput(self, size, type=None, resizeMode=ImgResizeMode.CROP, fps=None, enableUndistortion=None):
        if self.sensor is None:
            raise RuntimeError("Camera node must be built before requesting outputs")
        out = _Output(self, tuple(size), resizeMode)
        self.outputs.append(out)
        return out


class _Node:
    Camera = _CameraNode


class FakeDai:
    """Stands in for the `depthai` module over a set of `Hardware` on the bus."""

    CameraBoardSocket = CameraBoardSocket
    Platform = Platform
    ExternalFrameSyncRole = ExternalFrameSyncRole
    CameraExposureOffset = CameraExposureOffset
    ImgResizeMode = ImgResizeMode
    ImgFrame = ImgFrame
    CameraControl = CameraControl
    MessageQueue = MessageQueue
    DeviceInfo = DeviceInfo
    node = _Node

    def __init__(self, *hardware: Hardware):
        self.hardware = {h.device_id: h for h in hardware}
        self.opened: list[Device] = []
        self.pipelines: list[Pipeline] = []
        fake = self

        class _Device(Device):
            _fake = fake

        class _Pipeline(Pipeline):
            _fake = fake

        self.Device = _Device
        self.Pipeline = _Pipeline


class Device:
    _fake: FakeDai

    def __init__(self, info):
        device_id = info.getDeviceId() if isinstance(info, DeviceInfo) else str(info)
        hw = self._fake.hardware.get(device_id)
        if hw is None or not hw.plugged:
            raise RuntimeError(f"No available devices (cannot find device with id {device_id})")
        if hw.holder is not None and not hw.holder.isClosed():
            raise RuntimeError(f"Cannot connect to device {device_id}: X_LINK_DEVICE_ALREADY_IN_USE")
        self._hw, self._closed, self._lost, self._role, self._pipelines = hw, False, False, None, 0
        hw.holder = self
        self._fake.opened.append(self)

    @classmethod
    def getAllAvailableDevices(cls):
        return [
            DeviceInfo(h.device_id, _XLINK[h.platform])
            for h in cls._fake.hardware.values()
            if h.plugged and (h.holder is None or h.holder.isClosed())
        ]

    @classmethod
    def getAllConnectedDevices(cls):
        return [
            DeviceInfo(
                h.device_id,
                _XLINK[h.platform],
                XLinkDeviceState.X_LINK_UNBOOTED if h.holder is None or h.holder.isClosed() else XLinkDeviceState.X_LINK_BOOTED,
            )
            for h in cls._fake.hardware.values()
            if h.plugged
        ]

    def _alive(self):
        if self._closed or self._lost:
            raise RuntimeError("Device already closed or disconnected")

    def isClosed(self):
        return self._closed or self._lost

    def close(self):
        self._closed = True

    def getDeviceId(self):
        return self._hw.device_id

    def getPlatform(self):
        self._alive()
        return getattr(Platform, self._hw.platform)

    def getProductName(self):
        return self._hw.product

    def getConnectedCameraFeatures(self):
        self._alive()
        return [CameraFeatures(s) for s in self._hw.sensors]

    def getCameraSensorNames(self):
        return {getattr(CameraBoardSocket, s.socket): s.name for s in self._hw.sensors}

    def readCalibration(self):
        self._alive()
        return CalibrationHandler(self._hw)

    def setExternalFrameSyncRole(self, role=ExternalFrameSyncRole.AUTO_DETECT):
        self._alive()
        if self._hw.platform != "RVC4":
            return False, "External frame sync role is only supported on RVC4 devices"
        if self._hw.sync_role_error:
            return False, self._hw.sync_role_error
        self._role = role
        return True, ""

    def getExternalFrameSyncRole(self):
        return self._role

    def getChipTemperature(self):
        self._alive()
        return type("Temp", (), {"average": 41.0})()


class Pipeline:
    _fake: FakeDai

    def __init__(self, defaultDevice: Device | None = None):
        if defaultDevice is None:
            avail = self._fake.Device.getAllAvailableDevices()
            if not avail:
                raise RuntimeError("No available devices")
            defaultDevice = self._fake.Device(avail[0])
        if defaultDevice.isClosed():
            raise RuntimeError("Device already closed or disconnected")
        self.device = defaultDevice
        self.nodes: list[_CameraNode] = []
        self.queues: list[_OutputQueue] = []
        self.running = False
        self.stopped = False
        self._fake.pipelines.append(self)

    def create(self, kind):
        node = kind(self)
        self.nodes.append(node)
        return node

    def getDefaultDevice(self):
        return self.device

    def start(self):
        if self.stopped or self.device.isClosed():
            raise RuntimeError("Device already closed or disconnected")
        if self.device._pipelines:
            raise RuntimeError("Pipeline is already running on the device")
        self.device._pipelines += 1
        self.running = True

    def isRunning(self):
        return self.running

    def stop(self):
        if not self.running:
            return
        for q in self.queues:
            q.closed = True
        self.device.close()  # PipelineImpl::stop closes the default device
        self.device._pipelines -= 1
        self.running, self.stopped = False, True

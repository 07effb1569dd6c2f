"""Luxonis OAK cameras through depthai's v3 API.

One driver per camera socket of a device. Exposure, gain, white balance and focus are either fixed
from rig.toml or converged once and then locked, so every view of a capture agrees
photometrically. Sync is "software" (the stream runs; the first frame exposed after the trigger is
taken) or "fsin" (snapshot mode: the sensor exposes one frame per rising edge on its FSIN pin,
wired to the photo-eye). The device's factory calibration is the starting intrinsics guess.

The `dai` module is a parameter (default: the real import) so tests run against a fake of the
few objects used here; building a real `dai.Pipeline()` without a device blocks, then raises.
"""

from __future__ import annotations

import datetime as dt
import time

import numpy as np

from calibration.camera import Camera
from rig.camera import CameraError, CameraSettings, Frame, Health, register_driver

_OPENCV_DIST_SIZES = (0, 4, 5, 8, 12)


def import_depthai():
    try:
        import depthai
    except ImportError as e:  # pragma: no cover - depthai is a declared dependency
        raise CameraError(f"OAK cameras need the depthai package ({e})") from None
    return depthai


def list_oak_devices(dai=None) -> list[dict]:
    """Devices depthai can see: [{"device_id", "name", "state"}] (empty without any)."""
    dai = dai or import_depthai()
    return [{"device_id": info.getDeviceId(), "name": info.name, "state": getattr(info.state, "name", str(info.state))} for info in dai.Device.getAllAvailableDevices()]


def opencv_distortion(coeffs) -> np.ndarray:
    """depthai's [k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4 tx ty] -> the shortest OpenCV vector (0/4/5/8/12) that holds them.

    The sensor-tilt terms (tx, ty) are not part of our camera model; a device with non-zero tilt is refused.
    """
    c = np.asarray(coeffs, np.float64).reshape(-1)
    if c.size > 12 and np.any(c[12:]):
        raise CameraError("the device's calibration uses sensor tilt (tauX, tauY), which the camera model does not support")
    c = c[:12]
    nz = np.flatnonzero(c)
    need = 0 if nz.size == 0 else nz[-1] + 1
    size = next(s for s in _OPENCV_DIST_SIZES if s >= need)
    out = np.zeros(size)
    out[: min(size, c.size)] = c[:size]
    return out


def factory_camera(calibration, socket, width: int, height: int, c2w: np.ndarray | None = None) -> Camera:
    """The device's factory intrinsics at `width` x `height` as our Camera (principal point moved to +0.5 pixel centres)."""
    k = np.array(calibration.getCameraIntrinsics(socket, width, height), np.float64)
    k[0, 2] += 0.5  # OpenCV calibrations put pixel centres at integers; ours are at +0.5
    k[1, 2] += 0.5
    return Camera(k, width, height, opencv_distortion(calibration.getDistortionCoefficients(socket)), np.eye(4) if c2w is None else c2w)


def _ns(td: dt.timedelta) -> int:
    return (td.days * 86_400 + td.seconds) * 1_000_000_000 + td.microseconds * 1_000


@register_driver("oak")
class OakCamera:
    """Camera `socket` ("CAM_A", ...) of the OAK device `device_id`.

    `c2w`: its pose in the rig frame from the rig calibration (identity until calibrated).
    `converge_s`: how long auto exposure/white balance run before they are locked.
    """

    def __init__(self, camera_id: str, device_id: str, *, socket: str = "CAM_A", c2w: np.ndarray | None = None, camera: Camera | None = None, converge_s: float = 1.0, dai=None) -> None:
        self.camera_id = camera_id
        self.device_id = device_id
        self.socket = socket
        self.converge_s = converge_s
        self._c2w = np.eye(4) if c2w is None else np.asarray(c2w, np.float64)
        self._calibrated = camera
        self._dai = dai
        self._device = None
        self._pipeline = None
        self._queue = None
        self._control = None
        self._camera: Camera | None = camera
        self._settings: CameraSettings | None = None
        self._armed_ns = 0
        self._frames = 0
        self._errors = 0

    @property
    def dai(self):
        if self._dai is None:
            self._dai = import_depthai()
        return self._dai

    @property
    def camera(self) -> Camera:
        if self._camera is None:
            raise CameraError(f"{self.camera_id}: configure the OAK camera before asking for its model")
        return self._camera

    def _socket(self):
        try:
            return getattr(self.dai.CameraBoardSocket, self.socket)
        except AttributeError:
            raise CameraError(f"{self.camera_id}: unknown camera socket '{self.socket}' (use CAM_A, CAM_B, ...)") from None

    def open(self) -> None:
        dai = self.dai
        try:
            self._device = dai.Device(dai.DeviceInfo(self.device_id))
        except RuntimeError as e:
            raise CameraError(f"{self.camera_id}: OAK device {self.device_id} not found or busy ({e})") from None
        self._errors = 0

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Build and start the device pipeline; returns the settings in force, auto values resolved and locked."""
        if self._device is None:
            raise CameraError(f"{self.camera_id}: open the OAK camera before configuring it")
        if settings.sync not in ("software", "fsin"):
            raise CameraError(f"{self.camera_id}: sync must be 'software' or 'fsin', got '{settings.sync}'")
        if settings.sync == "fsin" and not settings.locked:
            raise CameraError(f"{self.camera_id}: sync 'fsin' needs fixed exposure_us, iso and white_balance_k (the sensor only exposes on trigger edges, so auto exposure cannot converge)")
        dai = self.dai
        self._stop_pipeline()
        socket = self._socket()
        try:
            pipeline = dai.Pipeline(self._device)
            node = pipeline.create(dai.node.Camera).build(socket)
            ctrl = node.initialControl
            if settings.sync == "fsin":
                ok, why = self._device.setExternalFrameSyncRole(dai.ExternalFrameSyncRole.SLAVE)
                if not ok:
                    raise CameraError(f"{self.camera_id}: the device refused external frame sync ({why})")
                ctrl.setExternalTrigger(1, 0)
            if settings.locked:
                ctrl.setManualExposure(int(settings.exposure_us), int(settings.iso))
                ctrl.setManualWhiteBalance(int(settings.white_balance_k))
            if settings.focus is not None:
                ctrl.setManualFocus(int(settings.focus))
            output = node.requestOutput((settings.width, settings.height), dai.ImgFrame.Type.BGR888i)
            self._queue = output.createOutputQueue(maxSize=4, blocking=False)
            self._control = node.inputControl.createInputQueue()
            pipeline.start()
            self._pipeline = pipeline
            calibration = self._device.readCalibration()
        except RuntimeError as e:
            raise CameraError(f"{self.camera_id}: OAK {self.device_id} could not start its camera pipeline ({e})") from None
        if self._calibrated is not None:
            self._camera = self._calibrated.scaled(settings.width, settings.height)
        else:
            self._camera = factory_camera(calibration, socket, settings.width, settings.height, self._c2w)
        self._settings = settings if settings.locked else self._converge_and_lock(settings)
        return self._settings

    def _converge_and_lock(self, settings: CameraSettings) -> CameraSettings:
        """Let auto exposure/white balance (and focus, unless fixed) run, then lock what they chose."""
        deadline = time.monotonic() + self.converge_s
        last = None
        while time.monotonic() < deadline or last is None:
            if time.monotonic() > deadline + 5.0:
                raise CameraError(f"{self.camera_id}: OAK {self.device_id} sent no frame while converging exposure")
            last = self._next_message(0.2) or last
        lock = self.dai.CameraControl()
        exposure_us = _ns(last.getExposureTime()) // 1000
        iso = int(last.getSensitivity())
        wb = int(last.getColorTemperature())
        lock.setManualExposure(int(exposure_us), iso)
        lock.setManualWhiteBalance(wb)
        focus = settings.focus
        if focus is None and last.getLensPosition() >= 0:
            focus = int(last.getLensPosition())
            lock.setManualFocus(focus)
        self._control.send(lock)
        return CameraSettings(settings.width, settings.height, int(exposure_us), iso, wb, focus, settings.sync)

    def _next_message(self, timeout_s: float):
        if self._device is None or self._device.isClosed():
            raise CameraError(f"{self.camera_id}: OAK {self.device_id} is disconnected")
        try:
            return self._queue.get(dt.timedelta(seconds=timeout_s))
        except (RuntimeError, self.dai.MessageQueue.QueueException) as e:
            self._errors += 1
            raise CameraError(f"{self.camera_id}: OAK {self.device_id} stopped delivering frames ({e})") from None

    def arm(self, seq: int) -> None:
        """Drop frames exposed before this trigger."""
        if self._queue is None:
            raise CameraError(f"{self.camera_id}: configure the OAK camera before arming it")
        try:
            self._queue.tryGetAll()
        except (RuntimeError, self.dai.MessageQueue.QueueException) as e:
            self._errors += 1
            raise CameraError(f"{self.camera_id}: OAK {self.device_id} is disconnected ({e})") from None
        self._armed_ns = time.monotonic_ns()

    def grab(self, timeout_s: float) -> Frame:
        """The first frame exposed after `arm` (depthai timestamps share the host's monotonic clock)."""
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                self._errors += 1
                raise CameraError(f"{self.camera_id}: no frame from OAK {self.device_id} within {timeout_s:.1f} s")
            msg = self._next_message(left)
            if msg is None:
                continue
            ts = _ns(msg.getTimestamp())
            if self._settings is not None and self._settings.sync == "software" and ts < self._armed_ns:
                continue
            image = np.ascontiguousarray(msg.getCvFrame()[..., ::-1])
            self._frames += 1
            settings = {
                "exposure_us": _ns(msg.getExposureTime()) // 1000,
                "iso": int(msg.getSensitivity()),
                "white_balance_k": int(msg.getColorTemperature()),
                "focus": int(msg.getLensPosition()),
                "sync": self._settings.sync if self._settings else "software",
                "device_seq": int(msg.getSequenceNum()),
                "device_id": self.device_id,
            }
            return Frame(self.camera_id, image, ts, settings)

    def _stop_pipeline(self) -> None:
        pipeline, self._pipeline = self._pipeline, None
        if pipeline is not None:
            try:
                pipeline.stop()
            except RuntimeError:
                pass

    def close(self) -> None:
        self._stop_pipeline()
        device, self._device = self._device, None
        if device is not None:
            try:
                device.close()
            except RuntimeError:
                pass

    def health(self) -> Health:
        if self._device is None or self._device.isClosed():
            return Health(self.camera_id, False, f"OAK {self.device_id} not connected", self._frames, self._errors)
        try:
            temp = self._device.getChipTemperature().average
            detail = f"OAK {self.device_id} {self.socket}, chip {temp:.0f} C"
        except RuntimeError as e:
            return Health(self.camera_id, False, f"OAK {self.device_id} not responding ({e})", self._frames, self._errors)
        return Health(self.camera_id, True, detail, self._frames, self._errors)

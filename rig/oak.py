"""Luxonis OAK cameras through depthai's v3 API.

One driver per camera socket; the sockets of one physical device share its `dai.Device` and
pipeline through `rig.oak_devices` (depthai opens a device once, and `Pipeline.stop()` closes it).
Exposure, gain, white balance and focus are either fixed from rig.toml or converged once and then
locked, so every view of a capture agrees photometrically. Sync is "software" (the stream runs; the
first frame whose exposure starts after the trigger is taken) or "fsin" (RVC2: snapshot mode, the
sensor exposes one frame per rising edge on FSIN, wired to the photo-eye; RVC4: the device follows
an external FSYNC as slave and the first frame exposed after the trigger is taken).

Times: depthai's `ImgFrame.getTimestamp()` is the end of exposure (readout start) on the host's
monotonic clock; a frame's time here is its exposure start, `getTimestamp(CameraExposureOffset.START)`.
Intrinsics are those of the delivered output (`ImgFrame.getTransformation()`), which differ from the
sensor's calibration scaled to the output size when the sensor mode or the output crops.

The `dai` module is a parameter (default: the real import) so tests run against a fake of depthai.
"""

from __future__ import annotations

import datetime as dt
import logging
import time

import numpy as np

from calibration.camera import Camera
from rig.camera import CameraError, CameraSettings, Frame, Health
from rig.oak_devices import Control, OakDevice, SocketSpec, device_for, release, sync_modes

log = logging.getLogger(__name__)

_OPENCV_DIST_SIZES = (0, 4, 5, 8, 12)
# The delivered frame's intrinsics may differ from the rig calibration by this much (focal, or principal point as a fraction of the size) before it is a warning.
INTRINSICS_TOLERANCE = 0.02


def import_depthai():
    try:
        import depthai
    except ImportError as e:  # pragma: no cover - depthai is a declared dependency
        raise CameraError(f"OAK cameras need the depthai package ({e})") from None
    return depthai


def _name(enum_value) -> str:
    return getattr(enum_value, "name", str(enum_value).rsplit(".", 1)[-1])


# DeviceInfo.platform is an XLinkPlatform; Device.getPlatform() a Platform. Say both the same way.
_XLINK_PLATFORMS = {"X_LINK_MYRIAD_X": "RVC2", "X_LINK_RVC3": "RVC3", "X_LINK_RVC4": "RVC4", "X_LINK_MYRIAD_2": "RVC1"}


def list_oak_devices(dai=None) -> list[dict]:
    """Devices depthai can see: [{"device_id", "name", "state", "platform"}] (empty without any)."""
    dai = dai or import_depthai()
    return [
        {
            "device_id": info.getDeviceId(),
            "name": info.name,
            "state": _name(info.state),
            "platform": _XLINK_PLATFORMS.get(_name(info.platform), _name(info.platform)),
        }
        for info in dai.Device.getAllConnectedDevices()
    ]


def describe_oak_device(device_id: str, dai=None) -> dict:
    """A device's product, platform and sockets [{"socket", "sensor", "width", "height", "sync"}], read by opening it briefly."""
    dai = dai or import_depthai()
    try:
        device = dai.Device(dai.DeviceInfo(device_id))
    except RuntimeError as e:
        raise CameraError(
            f"OAK {device_id} cannot be opened to list its cameras ({str(e).splitlines()[0]}); is a rig running on it?"
        ) from None
    try:
        platform = _name(device.getPlatform())
        sockets = [
            {
                "socket": _name(f.socket),
                "sensor": str(f.sensorName),
                "width": int(f.width),
                "height": int(f.height),
                "sync": sync_modes(platform, str(f.sensorName)),
            }
            for f in device.getConnectedCameraFeatures()
        ]
        product = str(device.getProductName())
    except RuntimeError as e:
        raise CameraError(f"OAK {device_id} did not describe its cameras ({str(e).splitlines()[0]})") from None
    finally:
        device.close()
    return {"device_id": device_id, "product": product, "platform": platform, "sockets": sorted(sockets, key=lambda s: s["socket"])}


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


def _opencv_k(k) -> np.ndarray:
    """depthai's 3x3 intrinsics (pixel centres at integers, OpenCV) -> ours (pixel centres at +0.5)."""
    k = np.array(k, np.float64)
    k[0, 2] += 0.5
    k[1, 2] += 0.5
    return k


def factory_camera(calibration, socket, width: int, height: int, c2w: np.ndarray | None = None) -> Camera:
    """The device's factory intrinsics at `width` x `height` as our Camera (principal point moved to +0.5 pixel centres)."""
    k = _opencv_k(calibration.getCameraIntrinsics(socket, width, height))
    return Camera(k, width, height, opencv_distortion(calibration.getDistortionCoefficients(socket)), np.eye(4) if c2w is None else c2w)


def frame_camera(transformation, c2w: np.ndarray) -> Camera:
    """The camera of a delivered frame: its ImgTransformation's intrinsics and distortion at its size."""
    w, h = transformation.getSize()
    return Camera(
        _opencv_k(transformation.getIntrinsicMatrix()), int(w), int(h), opencv_distortion(transformation.getDistortionCoefficients()), c2w
    )


def intrinsics_mismatch(expected: Camera, delivered: Camera, tolerance: float = INTRINSICS_TOLERANCE) -> str:
    """'' when the two agree; else one sentence saying how (focal ratio, principal point offset in pixels)."""
    ke, kd = expected.K, delivered.K
    focal = max(abs(kd[0, 0] / ke[0, 0] - 1), abs(kd[1, 1] / ke[1, 1] - 1))
    pp = max(abs(kd[0, 2] - ke[0, 2]) / delivered.width, abs(kd[1, 2] - ke[1, 2]) / delivered.height)
    if focal <= tolerance and pp <= tolerance:
        return ""
    return (
        f"the delivered {delivered.width}x{delivered.height} frames have fx {kd[0, 0]:.1f}, cx {kd[0, 2]:.1f}, cy {kd[1, 2]:.1f} "
        f"but the rig calibration at that size has fx {ke[0, 0]:.1f}, cx {ke[0, 2]:.1f}, cy {ke[1, 2]:.1f}: recalibrate at this output size"
    )


def _ns(td: dt.timedelta) -> int:
    return (td.days * 86_400 + td.seconds) * 1_000_000_000 + td.microseconds * 1_000


class OakCamera:
    """Camera `socket` ("CAM_A", ...) of the OAK device `device_id`.

    `c2w`: its pose in the rig frame from the rig calibration (identity until calibrated).
    `camera`: the rig calibration's model (else the delivered frames' own intrinsics are used).
    `converge_s`: how long auto exposure/white balance run before they are locked.
    `fsin_discard`: frames dropped after each FSIN edge (RVC2 snapshot), as their quality may be degraded.
    `fsin_lookback_s`: in snapshot mode, how long before `arm` a frame may have been exposed and still
    belong to this trigger (the trigger message reaches the host after the photo-eye edge).
    """

    def __init__(
        self,
        camera_id: str,
        device_id: str,
        *,
        socket: str = "CAM_A",
        c2w: np.ndarray | None = None,
        camera: Camera | None = None,
        converge_s: float = 1.0,
        fsin_discard: int = 0,
        fsin_lookback_s: float = 0.25,
        dai=None,
        device_options: dict | None = None,
    ) -> None:
        self.camera_id = camera_id
        self.device_id = device_id
        self.socket = socket
        self.converge_s = converge_s
        self.fsin_discard = fsin_discard
        self.fsin_lookback_ns = int(fsin_lookback_s * 1e9)
        self._c2w = np.eye(4) if c2w is None else np.asarray(c2w, np.float64)
        self._calibrated = camera
        self._dai = dai
        self._device_options = device_options or {}
        self._device: OakDevice | None = None
        self._camera: Camera | None = camera
        self._settings: CameraSettings | None = None
        self._armed_ns = 0
        self._held: list = []  # snapshot frames exposed within the lookback before `arm`
        self._frames = 0
        self._errors = 0
        self.straddling = 0  # frames discarded because their exposure began before the trigger
        self.calibration_warning = ""
        self._checked_k: tuple | None = None

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

    @property
    def reconnecting(self) -> bool:
        """The device dropped and is being re-opened in the background; captures are refused until it is back."""
        return self._device is not None and self._device.reconnecting

    @property
    def snapshot(self) -> bool:
        return self._settings is not None and self._settings.sync == "fsin" and self._device is not None and self._device.platform == "RVC2"

    def open(self) -> None:
        if self._device is not None:
            return
        if not hasattr(self.dai.CameraBoardSocket, self.socket):
            raise CameraError(f"{self.camera_id}: unknown camera socket '{self.socket}' (use CAM_A, CAM_B, ...)")
        device = device_for(self.device_id, self.dai, **self._device_options)
        try:
            device.attach(self.socket, self.camera_id)
        except CameraError as e:
            if not device.users:
                release(device, self.socket)
            msg = str(e)
            raise CameraError(msg if msg.startswith(f"{self.camera_id}:") else f"{self.camera_id}: {msg}") from None
        self._device = device
        self._errors = 0

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Set this socket's output and controls; returns the settings in force, auto values resolved and locked."""
        if self._device is None:
            raise CameraError(f"{self.camera_id}: open the OAK camera before configuring it")
        if settings.sync not in ("software", "fsin"):
            raise CameraError(f"{self.camera_id}: sync must be 'software' or 'fsin', got '{settings.sync}'")
        if settings.sync == "fsin" and not settings.locked:
            raise CameraError(
                f"{self.camera_id}: sync 'fsin' needs fixed exposure_us, iso and white_balance_k (the sensor only exposes on trigger edges, so auto exposure cannot converge)"
            )
        spec = SocketSpec(settings.width, settings.height, settings.sync, self.fsin_discard if settings.sync == "fsin" else 0)
        try:
            self._device.configure(self.socket, spec, Control(settings.exposure_us, settings.iso, settings.white_balance_k, settings.focus))
        except CameraError:
            if self._device.reconnecting and settings.locked:
                self._settings = settings  # kept by the device for its rebuild: in force once it is back
            raise
        self._settings = settings
        if self._calibrated is not None:
            self._camera = self._calibrated.scaled(settings.width, settings.height)
        elif self._camera is None or (self._camera.width, self._camera.height) != (settings.width, settings.height):
            self._camera = None
        if not self.snapshot:
            # A streaming output: its first frame says which intrinsics are delivered.
            self._use_frame(self._next_message(5.0, "while starting"))
        elif self._camera is None:
            # No frame before the first trigger: the factory calibration at this size until one arrives.
            self._camera = factory_camera(
                self._device.calibration(), getattr(self.dai.CameraBoardSocket, self.socket), settings.width, settings.height, self._c2w
            )
        if not settings.locked:
            self._settings = self._converge_and_lock(settings)
        return self._settings

    def _converge_and_lock(self, settings: CameraSettings) -> CameraSettings:
        """Let auto exposure/white balance (and focus, unless fixed) run, then lock what they chose."""
        deadline = time.monotonic() + self.converge_s
        last = None
        while time.monotonic() < deadline or last is None:
            if time.monotonic() > deadline + 5.0:
                raise CameraError(f"{self.camera_id}: OAK {self.device_id} sent no frame while converging exposure")
            last = self._next_message(0.2, "while converging exposure") or last
        focus = settings.focus
        if focus is None and last.getLensPosition() >= 0:
            focus = int(last.getLensPosition())
        locked = CameraSettings(
            settings.width,
            settings.height,
            _ns(last.getExposureTime()) // 1000,
            int(last.getSensitivity()),
            int(last.getColorTemperature()),
            focus,
            settings.sync,
        )
        self._device.send(self.socket, Control(locked.exposure_us, locked.iso, locked.white_balance_k, locked.focus))
        return locked

    def _fail(self, error: Exception) -> CameraError:
        """A depthai error on the link: the device is lost (re-opened in the background)."""
        self._errors += 1
        if self._device is not None:
            self._device.lost(error)
            return CameraError(self._device.down_sentence(self.camera_id))
        return CameraError(f"{self.camera_id}: OAK {self.device_id} stopped delivering frames ({error})")

    def _next_message(self, timeout_s: float, doing: str = ""):
        """The next frame of this socket, None on timeout (a closed queue or a dropped link raises CameraError)."""
        if self._device is None:
            raise CameraError(f"{self.camera_id}: open the OAK camera first")
        q = self._device.queue(self.socket)
        try:
            msg = q.get(dt.timedelta(seconds=max(0.0, timeout_s)))
        except (RuntimeError, self.dai.MessageQueue.QueueException) as e:
            raise self._fail(e) from None
        if msg is None and doing:
            self._errors += 1
            raise CameraError(f"{self.camera_id}: OAK {self.device_id} sent no frame within {timeout_s:.1f} s {doing}")
        return msg

    def _use_frame(self, msg) -> None:
        """Take the delivered frame's intrinsics (checked against the rig calibration when there is one)."""
        try:
            tr = msg.getTransformation()
            key = tuple(np.asarray(tr.getIntrinsicMatrix(), np.float64).ravel()) + tuple(tr.getSize())
        except RuntimeError:
            return
        if key == self._checked_k:
            return
        self._checked_k = key
        delivered = frame_camera(tr, self._c2w)
        if self._calibrated is None:
            self._camera = delivered
            return
        self.calibration_warning = intrinsics_mismatch(self._calibrated.scaled(delivered.width, delivered.height), delivered)
        if self.calibration_warning:
            log.warning("%s: %s", self.camera_id, self.calibration_warning)

    def arm(self, seq: int) -> None:
        """Take the trigger as now: frames exposed before it are dropped (in snapshot mode: before now minus the lookback)."""
        if self._settings is None:
            raise CameraError(f"{self.camera_id}: configure the OAK camera before arming it")
        self._armed_ns = time.monotonic_ns()
        try:
            q = self._device.queue(self.socket)
            stale = q.tryGetAll()
        except (RuntimeError, self.dai.MessageQueue.QueueException) as e:
            raise self._fail(e) from None
        if self.snapshot:
            self._armed_ns -= self.fsin_lookback_ns
            self._held = [m for m in stale if _ns(m.getTimestamp(self.dai.CameraExposureOffset.START)) >= self._armed_ns]
        else:
            self._held = []

    def grab(self, timeout_s: float) -> Frame:
        """The first frame whose exposure started at or after the trigger (one that straddles it is discarded)."""
        deadline = time.monotonic() + timeout_s
        while True:
            if self._held:
                msg = self._held.pop(0)
            else:
                left = deadline - time.monotonic()
                if left <= 0:
                    self._errors += 1
                    raise CameraError(f"{self.camera_id}: no frame from OAK {self.device_id} within {timeout_s:.1f} s")
                msg = self._next_message(left)
                if msg is None:
                    continue
            start = _ns(msg.getTimestamp(self.dai.CameraExposureOffset.START))
            if start < self._armed_ns:
                if _ns(msg.getTimestamp()) >= self._armed_ns:
                    self.straddling += 1
                continue
            return self._frame(msg, start)

    def _frame(self, msg, start_ns: int) -> Frame:
        self._use_frame(msg)
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
            "socket": self.socket,
            "exposure_start_ns": start_ns,
            "readout_ns": _ns(msg.getTimestamp()),
            "straddling_discarded": self.straddling,
        }
        if self.calibration_warning:
            settings["calibration_warning"] = self.calibration_warning
        return Frame(self.camera_id, image, start_ns, settings)

    def close(self) -> None:
        device, self._device = self._device, None
        self._settings = None
        if device is not None:
            release(device, self.socket)

    def health(self) -> Health:
        dev = self._device
        if dev is None:
            return Health(self.camera_id, False, f"OAK {self.device_id} {self.socket} not open", self._frames, self._errors)
        if not dev.up:
            return Health(self.camera_id, False, dev.down_sentence(self.camera_id).split(": ", 1)[1], self._frames, self._errors)
        try:
            temp = dev.chip_temperature()
        except (CameraError, RuntimeError) as e:
            return Health(self.camera_id, False, f"OAK {self.device_id} not responding ({e})", self._frames, self._errors)
        sensor = dev.sensors.get(self.socket, "")
        detail = f"OAK {self.device_id} {self.socket} {sensor} ({dev.platform}), chip {temp:.0f} C"
        if self.calibration_warning:
            detail += "; calibration warning: " + self.calibration_warning
        return Health(self.camera_id, True, detail, self._frames, self._errors)

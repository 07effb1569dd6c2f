"""One `dai.Device` and one pipeline per physical OAK, shared by the drivers of its camera sockets.

depthai allows one open per device, and `Pipeline.stop()` closes the pipeline's device
(depthai-core `PipelineImpl::stop`), so a pipeline is never rebuilt on the old `Device`: every
rebuild stops the pipeline, opens the device anew and starts one pipeline with a Camera node for
every socket in use. Exposure, gain, white balance and focus changes go to the running pipeline's
control queues without a rebuild; size and sync changes rebuild.

A device whose link drops (X_LINK_ERROR, a USB reset) is re-opened in the background with
back-off, its pipeline rebuilt as it was, while its sockets report themselves down.

Sync per platform: RVC2 takes snapshot sync (`setFrameSyncMode(INPUT)` + `setExternalTrigger`, one
frame per rising edge on FSIN) on the sensors depthai supports it for; RVC4 takes the device's
external frame-sync role (`setExternalFrameSyncRole(SLAVE)`: a continuous FSYNC from the M8 line).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

from rig.camera import CameraError

log = logging.getLogger(__name__)

# Snapshot mode (external trigger) per depthai's frame-sync docs; other sensors free-run (e.g. IMX296, depthai-core #895).
SNAPSHOT_SENSORS = ("OV9282", "OV9782", "AR0234")
SHUTTER = {
    "OV9282": "global-shutter",
    "OV9782": "global-shutter",
    "AR0234": "global-shutter",
    "OV7251": "global-shutter",
    "IMX296": "global-shutter",
    "IMX378": "rolling-shutter",
    "IMX477": "rolling-shutter",
    "IMX577": "rolling-shutter",
    "IMX380": "rolling-shutter",
    "IMX582": "rolling-shutter",
    "IMX586": "rolling-shutter",
    "IMX214": "rolling-shutter",
    "IMX412": "rolling-shutter",
    "IMX462": "rolling-shutter",
    "IMX258": "rolling-shutter",
}


@dataclass(frozen=True)
class SocketSpec:
    """What a socket's Camera node and output are built with (changing any of it rebuilds the pipeline)."""

    width: int
    height: int
    sync: str = "software"
    fsin_discard: int = 0


@dataclass(frozen=True)
class Control:
    """Photometric control of one socket (None: left to the camera's auto algorithms)."""

    exposure_us: int | None = None
    iso: int | None = None
    white_balance_k: int | None = None
    focus: int | None = None

    def apply(self, ctrl) -> None:
        if self.exposure_us is not None and self.iso is not None:
            ctrl.setManualExposure(int(self.exposure_us), int(self.iso))
        if self.white_balance_k is not None:
            ctrl.setManualWhiteBalance(int(self.white_balance_k))
        if self.focus is not None:
            ctrl.setManualFocus(int(self.focus))


def sync_modes(platform: str, sensor: str) -> list[str]:
    """Sync modes a sensor supports on a platform: 'software' always; 'fsin' as snapshot (RVC2) or device slave (RVC4)."""
    if platform == "RVC2" and sensor.upper() in SNAPSHOT_SENSORS:
        return ["software", "fsin (snapshot on FSIN edge)"]
    if platform == "RVC4":
        return ["software", "fsin (continuous FSYNC, device slave)"]
    return ["software"]


def refuse_sync(platform: str, socket: str, sensor: str) -> str:
    """Why `sensor` on `socket` cannot take sync = 'fsin' on `platform` ('' if it can)."""
    if platform == "RVC4":
        return ""
    if platform != "RVC2":
        return f"{socket}: hardware frame sync is not supported on {platform} devices, use sync = 'software'"
    if sensor.upper() in SNAPSHOT_SENSORS:
        return ""
    kind = SHUTTER.get(sensor.upper(), "")
    what = f"a {kind} {sensor}" if kind else f"an {sensor}" if sensor[:1] in "AEIOU" else f"a {sensor}"
    return f"{socket} is {what}: snapshot sync is not supported (only {', '.join(SNAPSHOT_SENSORS)}), use sync = 'software'"


@dataclass
class _Link:
    """The live depthai objects of one build."""

    device: object
    pipeline: object
    queues: dict = field(default_factory=dict)
    controls: dict = field(default_factory=dict)


class OakDevice:
    """The physical OAK `device_id`, shared by the sockets attached to it.

    `reopen_s`: how long a re-open waits for the device to come back after `Pipeline.stop()` closed it
    (a USB device reboots). `backoff_s`: first and longest wait between background reconnection attempts.
    """

    def __init__(self, device_id: str, dai, *, reopen_s: float = 10.0, backoff_s: tuple[float, float] = (0.5, 30.0)) -> None:
        self.device_id = device_id
        self.dai = dai
        self.reopen_s = reopen_s
        self.backoff_s = backoff_s
        self.users: dict[str, str] = {}  # socket -> camera id
        self.specs: dict[str, SocketSpec] = {}
        self.controls: dict[str, Control] = {}
        self.platform = ""
        self.product = ""
        self.sensors: dict[str, str] = {}  # socket -> sensor name
        self.lost_reason = ""
        self.attempts = 0
        self.reconnects = 0
        self._link: _Link | None = None
        self._device = None  # open, no pipeline yet
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ---- sockets ---------------------------------------------------------------------------

    def attach(self, socket: str, camera_id: str) -> None:
        with self._lock:
            if socket in self.users:
                raise CameraError(
                    f"{camera_id}: {socket} of OAK {self.device_id} is already camera {self.users[socket]}; one camera per socket"
                )
            if self.reconnecting:
                self.users[socket] = camera_id
                return
            if self._device is None and self._link is None:
                self._device = self._open(wait_s=0.0)
                self._describe(self._device)
            if socket not in self.sensors:
                known = ", ".join(f"{s} ({n})" for s, n in sorted(self.sensors.items())) or "none"
                if not self.users and self._link is None:
                    self._close_quietly(self._device)
                    self._device = None
                raise CameraError(f"{camera_id}: OAK {self.device_id} has no camera on {socket} (connected: {known})")
            self.users[socket] = camera_id

    def detach(self, socket: str) -> bool:
        """Release a socket; the last one closes the device. True when the device is released."""
        with self._lock:
            self.users.pop(socket, None)
            self.specs.pop(socket, None)
            self.controls.pop(socket, None)
            if self.users:
                return False
            self._stop.set()
            self._teardown()
            self._close_quietly(self._device)
            self._device = None
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5)
        return True

    def configure(self, socket: str, spec: SocketSpec, control: Control) -> None:
        """Set a socket's output and control. Sockets attached but not yet configured take the same
        spec, so configuring a rig's cameras one after another with one size builds the pipeline once."""
        with self._lock:
            camera_id = self.users[socket]
            if spec.sync == "fsin":
                why = refuse_sync(self.platform, socket, self.sensors.get(socket, "?"))
                if why:
                    raise CameraError(f"{camera_id}: {why}")
            self.controls[socket] = control
            if self.reconnecting:
                self.specs[socket] = spec
                raise CameraError(self.down_sentence(camera_id))
            wanted = {s: self.specs.get(s) or self._like(s, spec) for s in self.users}
            wanted[socket] = spec
            if self._link is not None and wanted == self.specs:
                self._send(socket, control)
                return
            previous, self.specs = self.specs, wanted
            try:
                self._rebuild(camera_id)
            except CameraError:
                self.specs = previous  # the refused spec is not kept for the next rebuild
                raise

    def _like(self, socket: str, spec: SocketSpec) -> SocketSpec:
        """`spec` for a socket not configured yet (software sync where its sensor cannot take fsin)."""
        if spec.sync == "fsin" and refuse_sync(self.platform, socket, self.sensors.get(socket, "?")):
            return SocketSpec(spec.width, spec.height)
        return spec

    def queue(self, socket: str):
        """The socket's output queue; CameraError while the device is down."""
        with self._lock:
            if self._link is None or socket not in self._link.queues:
                raise CameraError(self.down_sentence(self.users.get(socket, socket)))
            return self._link.queues[socket]

    def send(self, socket: str, control: Control) -> None:
        with self._lock:
            self.controls[socket] = control
            self._send(socket, control)

    # ---- state -----------------------------------------------------------------------------

    @property
    def up(self) -> bool:
        return self._link is not None

    @property
    def reconnecting(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def down_sentence(self, camera_id: str) -> str:
        if self.reconnecting:
            tried = f", {self.attempts} attempts so far" if self.attempts else ""
            return f"{camera_id}: OAK {self.device_id} is disconnected ({self.lost_reason}); reconnecting in the background{tried}"
        return f"{camera_id}: OAK {self.device_id} is not running (configure the camera first)"

    def calibration(self):
        """The device's factory calibration (a depthai CalibrationHandler)."""
        with self._lock:
            if self._link is None:
                raise CameraError(f"OAK {self.device_id} is not running")
            try:
                return self._link.device.readCalibration()
            except RuntimeError as e:
                raise CameraError(f"OAK {self.device_id} did not give its calibration ({_short(e)})") from None

    def chip_temperature(self) -> float:
        """The chip's temperature; also how an idle device's lost link is noticed (health checks poll it)."""
        with self._lock:
            if self._link is None:
                raise CameraError(f"OAK {self.device_id} is not running")
            try:
                return float(self._link.device.getChipTemperature().average)
            except RuntimeError as e:
                self.lost(e)
                raise CameraError(f"OAK {self.device_id} is disconnected ({self.lost_reason}); reconnecting in the background") from None

    def lost(self, error: Exception | str) -> None:
        """The link dropped: drop the dead objects and re-open in the background with back-off."""
        with self._lock:
            if self.reconnecting or self._stop.is_set() or not self.users:
                return
            self.lost_reason = _short(error)
            log.warning("OAK %s lost: %s; reconnecting", self.device_id, self.lost_reason)
            self._teardown()
            self.attempts = 0
            self._thread = threading.Thread(target=self._reconnect, name=f"oak-reconnect-{self.device_id}", daemon=True)
            self._thread.start()

    # ---- depthai ---------------------------------------------------------------------------

    def _open(self, wait_s: float):
        dai = self.dai
        deadline = time.monotonic() + wait_s
        while True:
            try:
                return dai.Device(dai.DeviceInfo(self.device_id))
            except RuntimeError as e:
                if time.monotonic() >= deadline:
                    raise CameraError(f"OAK {self.device_id} not found or busy ({_short(e)})") from None
            time.sleep(0.25)

    def _describe(self, device) -> None:
        try:
            self.platform = _name(device.getPlatform())
            self.sensors = {_name(f.socket): str(f.sensorName) for f in device.getConnectedCameraFeatures()}
            self.product = str(device.getProductName()) if hasattr(device, "getProductName") else ""
        except RuntimeError as e:
            raise CameraError(f"OAK {self.device_id} did not describe its cameras ({_short(e)})") from None

    def _rebuild(self, camera_id: str) -> None:
        """Stop the running pipeline (which closes the device), re-open the device, start a pipeline with every socket."""
        dai = self.dai
        had_pipeline = self._link is not None
        self._teardown()
        device = self._device
        self._device = None
        if device is None or device.isClosed():
            try:
                device = self._open(self.reopen_s if had_pipeline else 0.0)
            except CameraError as e:
                raise CameraError(f"{camera_id}: {e}") from None
        try:
            if self.platform == "RVC4" and any(s.sync == "fsin" for s in self.specs.values()):
                ok, why = device.setExternalFrameSyncRole(dai.ExternalFrameSyncRole.SLAVE)
                if not ok:
                    raise CameraError(
                        f"{camera_id}: OAK {self.device_id} refused the external frame-sync role SLAVE ({why}); check the M8 sync cable, or use sync = 'software'"
                    )
            pipeline = dai.Pipeline(device)
            link = _Link(device, pipeline)
            for socket, spec in sorted(self.specs.items()):
                node = pipeline.create(dai.node.Camera).build(getattr(dai.CameraBoardSocket, socket))
                ctrl = node.initialControl
                if spec.sync == "fsin" and self.platform == "RVC2":
                    ctrl.setFrameSyncMode(dai.CameraControl.FrameSyncMode.INPUT)
                    ctrl.setExternalTrigger(1 + spec.fsin_discard, spec.fsin_discard)
                self.controls.get(socket, Control()).apply(ctrl)
                out = node.requestOutput((spec.width, spec.height), dai.ImgFrame.Type.BGR888i)
                link.queues[socket] = out.createOutputQueue(maxSize=8, blocking=False)
                link.controls[socket] = node.inputControl.createInputQueue()
            pipeline.start()
        except CameraError:
            self._close_quietly(device)
            raise
        except RuntimeError as e:
            self._close_quietly(device)
            raise CameraError(f"{camera_id}: OAK {self.device_id} could not start its camera pipeline ({_short(e)})") from None
        self._link = link

    def _ctrl(self):
        return self.dai.CameraControl()

    def _send(self, socket: str, control: Control) -> None:
        if self._link is None or socket not in self._link.controls:
            return
        ctrl = self._ctrl()
        control.apply(ctrl)
        try:
            self._link.controls[socket].send(ctrl)
        except RuntimeError as e:
            self.lost(e)
            raise CameraError(self.down_sentence(self.users.get(socket, socket))) from None

    def _teardown(self) -> None:
        link, self._link = self._link, None
        if link is None:
            return
        try:
            link.pipeline.stop()
        except RuntimeError:
            pass
        self._close_quietly(link.device)

    @staticmethod
    def _close_quietly(device) -> None:
        if device is not None:
            try:
                device.close()
            except RuntimeError:
                pass

    def _reconnect(self) -> None:
        delay = self.backoff_s[0]
        while not self._stop.wait(delay):
            with self._lock:
                if self._stop.is_set():
                    return
                self.attempts += 1
                try:
                    self._rebuild("reconnect")
                except CameraError as e:
                    log.info("OAK %s reconnect attempt %d: %s", self.device_id, self.attempts, e)
                else:
                    self.reconnects += 1
                    log.warning("OAK %s is back after %d attempts", self.device_id, self.attempts)
                    self._thread = None
                    return
            delay = min(self.backoff_s[1], delay * 2)


def _name(enum_value) -> str:
    return getattr(enum_value, "name", str(enum_value).rsplit(".", 1)[-1])


def _short(error: Exception | str) -> str:
    text = str(error)
    return "X_LINK_ERROR" if "X_LINK_ERROR" in text else text.splitlines()[0][:160] if text else type(error).__name__


_REGISTRY: dict[tuple[int, str], OakDevice] = {}
_REGISTRY_LOCK = threading.Lock()


def device_for(device_id: str, dai, **kw) -> OakDevice:
    """The shared OakDevice of `device_id` (one per depthai module, so tests with separate fakes stay apart)."""
    with _REGISTRY_LOCK:
        key = (id(dai), device_id)
        if key not in _REGISTRY:
            _REGISTRY[key] = OakDevice(device_id, dai, **kw)
        return _REGISTRY[key]


def release(device: OakDevice, socket: str) -> None:
    if device.detach(socket):
        with _REGISTRY_LOCK:
            if _REGISTRY.get((id(device.dai), device.device_id)) is device:
                del _REGISTRY[(id(device.dai), device.device_id)]

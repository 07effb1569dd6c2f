"""From a validated rig.toml to live objects: camera drivers, the trigger source, the store.

`DRIVERS` maps each rig.toml `driver` name to the driver it builds (the protocol is in
`rig.camera`; the drivers import only the protocol, never this table).

Also the simulated rig (`--simulate`): synthetic cameras rendering a part on the conveyor, and a
simulated PLC that sends triggers over a virtual CAN bus or a loop serial port, so the appliance
runs end to end without hardware through the same trigger code as in the field.
"""

from __future__ import annotations

import itertools
import json
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import serial

from calibration.camera import Camera
from rig.camera import CameraDriver, CameraError
from rig.config import CameraConfig, RigConfig, TriggerConfig
from rig.oak import OakCamera
from rig.replay import ReplayCamera
from rig.store import CaptureStore
from rig.synthetic_driver import PatternCamera, SyntheticRig, procedural_part
from rig.triggers import CanTrigger, SerialTrigger, SoftwareTrigger, TriggerSource, encode_can_trigger, format_trigger_line

REPO = Path(__file__).resolve().parents[1]


class RigCalibrationRef(NamedTuple):
    calibration_id: str  # names the version ("calibration-v0003") so every capture records which it was taken under
    cameras: dict[str, Camera]
    uncertainty: dict | None  # the worst camera's stated extrinsic uncertainty (calibfile.extrinsics_uncertainty)


def load_rig_calibration(path: Path | None) -> RigCalibrationRef:
    """The keeper's `calibration.json` for the rig; ("uncalibrated", {}, None) without one."""
    if path is None:
        return RigCalibrationRef("uncalibrated", {}, None)
    from calibration.calibfile import extrinsics_uncertainty, read_calibration

    doc = read_calibration(path)
    version = f"v{doc.version:04d}" if doc.version is not None else "unversioned"
    return RigCalibrationRef(f"{Path(path).stem}-{version}", dict(doc.cameras), extrinsics_uncertainty(doc))


# (camera's config, its calibrated model or None, its index, number of cameras) -> driver.
DriverFactory = Callable[[CameraConfig, Camera | None, int, int], CameraDriver]

DRIVERS: dict[str, DriverFactory] = {
    "oak": lambda cfg, calibrated, index, n: OakCamera(
        cfg.id, cfg.device, socket=cfg.socket, camera=calibrated, fsin_discard=cfg.fsin_discard
    ),
    "replay": lambda cfg, calibrated, index, n: ReplayCamera(cfg.id, cfg.path),
    "pattern": lambda cfg, calibrated, index, n: PatternCamera(
        cfg.id, index=index, n=n, width=cfg.settings.width, height=cfg.settings.height
    ),
}


def build_camera(cfg: CameraConfig, calibrated: Camera | None, index: int, n: int) -> CameraDriver:
    """The driver of camera `index` of `n` as rig.toml configures it."""
    if cfg.driver not in DRIVERS:
        raise CameraError(f"unknown camera driver '{cfg.driver}' (known: {', '.join(sorted(DRIVERS))})")
    return DRIVERS[cfg.driver](cfg, calibrated, index, n)


def build_cameras(cfg: RigConfig, calibration: dict[str, Camera]) -> list[CameraDriver]:
    return [build_camera(c, calibration.get(c.id), i, len(cfg.cameras)) for i, c in enumerate(cfg.cameras)]


def build_trigger(cfg: TriggerConfig) -> TriggerSource:
    if cfg.kind == "serial":
        return SerialTrigger(cfg.port, baudrate=cfg.baudrate, pattern=cfg.pattern)
    if cfg.kind == "can":
        return CanTrigger(
            interface=cfg.interface, channel=cfg.channel, arbitration_id=cfg.arbitration_id, payload_format=cfg.payload_format
        )
    return SoftwareTrigger()


def build_store(cfg: RigConfig, root: Path | None = None) -> CaptureStore:
    return CaptureStore(root or cfg.storage.root, min_free_bytes=int(cfg.storage.min_free_gb * 1e9))


def sample_mesh() -> Path | None:
    """The bundled sample's textured object mesh (sample/sample.json "mesh"), if this checkout has one."""
    manifest = REPO / "sample" / "sample.json"
    try:
        mesh = manifest.parent / json.loads(manifest.read_text())["mesh"]
    except (FileNotFoundError, json.JSONDecodeError, KeyError, TypeError):
        return None
    return mesh if mesh.is_file() else None


class SimulatedPlc:
    """The conveyor's PLC: a trigger every 1/rate s with a rising seq and encoder count, on a virtual
    CAN bus or a loop serial port. `source` is the matching trigger reader, as in the field."""

    def __init__(self, kind: str, rate_hz: float, *, encoder_per_part: int = 2048) -> None:
        if kind not in ("can", "serial"):
            raise ValueError(f"simulated trigger must be 'can' or 'serial', got '{kind}'")
        if not rate_hz > 0:
            raise ValueError(f"trigger rate must be positive, got {rate_hz}")
        self.kind, self.rate_hz, self.encoder_per_part = kind, rate_hz, encoder_per_part
        self.sent = 0
        self._stop = threading.Event()
        if kind == "can":
            import can

            channel = f"cadsplat-sim-{time.monotonic_ns()}"
            self.source: TriggerSource = CanTrigger(interface="virtual", channel=channel)
            self._bus = can.Bus(interface="virtual", channel=channel)
            self._send = lambda seq: self._bus.send(
                can.Message(arbitration_id=0x181, data=encode_can_trigger(seq, seq * encoder_per_part), is_extended_id=False)
            )
        else:
            port = serial.serial_for_url("loop://", timeout=0.05)
            self.source = SerialTrigger("loop://", open_port=lambda: port)
            self._bus = port
            self._send = lambda seq: port.write(format_trigger_line(seq, seq * encoder_per_part))
        self._thread = threading.Thread(target=self._run, name="simulated-plc", daemon=True)

    def start(self) -> SimulatedPlc:
        self.source.start()
        time.sleep(0.05)  # let the reader open its end before the first trigger
        self._thread.start()
        return self

    def _run(self) -> None:
        t0 = time.monotonic()
        for seq in itertools.count(1):
            if self._stop.wait(max(0.0, t0 + (seq - 0.5) / self.rate_hz - time.monotonic())):
                return
            self._send(seq)
            self.sent += 1

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.source.stop()
        if self.kind == "can":
            self._bus.shutdown()


def simulated_cameras(views: int, width: int, height: int, mesh: Path | None = None):
    """(drivers, rig) of the synthetic rig rendering `mesh` (default: the sample's, else a procedural part)."""
    part = mesh or sample_mesh() or procedural_part()
    rig = SyntheticRig.from_mesh(part, views, width=width, height=height)
    return rig.drivers(), rig

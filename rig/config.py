"""`rig.toml`: the rig's cameras, trigger, storage and thresholds, validated on load.

Every error names the key it is about (`cameras[2].width`, `trigger.kind`, ...) in one sentence.
See deploy/rig.example.toml for a commented example.
"""

from __future__ import annotations

import os
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path

import tomllib

from calibration.fileio import MAX_IMAGE_PIXELS
from rig.acquisition import Thresholds
from rig.camera import CameraSettings
from rig.triggers import DEFAULT_CAN_FORMAT, DEFAULT_SERIAL_PATTERN

CAMERA_DRIVERS = ("oak", "replay", "pattern")
TRIGGER_KINDS = ("serial", "can", "software")


class ConfigError(ValueError):
    """rig.toml is invalid; the message names the key."""


@dataclass(frozen=True)
class CameraConfig:
    id: str
    driver: str
    settings: CameraSettings
    device: str = ""  # OAK device id (MX id / serial)
    socket: str = "CAM_A"
    path: str = ""  # replay: a capture or a directory of captures
    fsin_discard: int = 0  # OAK snapshot sync: frames dropped after each FSIN edge (the first may be degraded)


@dataclass(frozen=True)
class TriggerConfig:
    kind: str = "software"
    port: str = ""
    baudrate: int = 115200
    pattern: str = DEFAULT_SERIAL_PATTERN
    interface: str = "socketcan"
    channel: str = "can0"
    arbitration_id: int = 0x181
    payload_format: str = DEFAULT_CAN_FORMAT
    debounce_ms: float = 5.0
    min_interval_ms: float = 0.0


@dataclass(frozen=True)
class StorageConfig:
    """`[storage]`: `spill` is where captures go that the store cannot take (it went read-only) before the rig
    stops; it must be on another filesystem than `root`. None: rig.store.default_spill_dir()."""

    root: Path = Path("captures")
    min_free_gb: float = 1.0
    spill: Path | None = None


@dataclass(frozen=True)
class InspectionConfig:
    """`[inspection]`: every twin is inspected against its CAD at `tolerance_mm`; `max_unseen_pct` None = inspect's default."""

    tolerance_mm: float
    max_unseen_pct: float | None = None


@dataclass(frozen=True)
class RigConfig:
    rig_id: str
    cameras: tuple[CameraConfig, ...]
    trigger: TriggerConfig = field(default_factory=TriggerConfig)
    storage: StorageConfig = field(default_factory=StorageConfig)
    thresholds: Thresholds = field(default_factory=Thresholds)
    calibration: Path | None = None
    # [registration] as written: reconstruction.registration.RegistrationConfig.from_dict reads and checks it (the rig
    # itself never registers, and rig never imports reconstruction), so its keys and defaults live in one place.
    registration: dict = field(default_factory=dict)
    # [simulation] as written, likewise: simulation.asset.rig_simulation_table checks it; captures carry its `up`.
    simulation: dict = field(default_factory=dict)
    inspection: InspectionConfig | None = None
    max_image_pixels: int = MAX_IMAGE_PIXELS  # [limits]: no image declaring more is decoded (calibration.fileio)


def load_config(path: str | os.PathLike) -> RigConfig:
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such rig config file") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML ({e})") from None
    return parse_config(doc, base=path.parent, name=path.name)


def parse_config(doc: dict, *, base: Path = Path("."), name: str = "rig.toml") -> RigConfig:
    """A validated RigConfig from a parsed TOML document; relative paths are relative to `base`."""
    v = _Validator(name)
    # [simulation] (material, density of exported twins) is read and checked by simulation.asset.rig_simulation_table.
    v.known(
        doc,
        "",
        {"rig_id", "calibration", "cameras", "trigger", "storage", "thresholds", "simulation", "registration", "inspection", "limits"},
    )
    rig_id = v.string(doc, "rig_id", default="rig")
    calibration = v.string(doc, "calibration", default="")
    cams_doc = doc.get("cameras")
    if not isinstance(cams_doc, list) or not cams_doc:
        raise ConfigError(f"{name}: cameras must be a non-empty array of tables ([[cameras]])")
    cameras = tuple(_camera(v, c, f"cameras[{i}]", base) for i, c in enumerate(cams_doc))
    ids = [c.id for c in cameras]
    dup = next((i for i in ids if ids.count(i) > 1), None)
    if dup:
        raise ConfigError(f"{name}: cameras[].id must be unique, '{dup}' appears twice")
    max_image_pixels = _max_image_pixels(v, v.table(doc, "limits"), cameras)
    return RigConfig(
        rig_id=rig_id,
        cameras=cameras,
        trigger=_trigger(v, v.table(doc, "trigger")),
        storage=_storage(v, v.table(doc, "storage"), base),
        thresholds=_thresholds(v, v.table(doc, "thresholds")),
        calibration=(base / calibration) if calibration else None,
        registration=dict(v.table(doc, "registration")),
        simulation=dict(v.table(doc, "simulation")),
        inspection=_inspection(v, v.table(doc, "inspection")) if "inspection" in doc else None,
        max_image_pixels=max_image_pixels,
    )


def _max_image_pixels(v: _Validator, d: dict, cameras: tuple[CameraConfig, ...]) -> int:
    """[limits] max_image_pixels: at least every camera's frame, and under PIL's own decompression-bomb limit."""
    v.known(d, "limits", {"max_image_pixels"})
    cap = v.integer(d, "limits.max_image_pixels", default=MAX_IMAGE_PIXELS, lo=1_000_000, hi=150_000_000)
    for i, c in enumerate(cameras):
        if c.settings.width * c.settings.height > cap:
            raise ConfigError(
                f"{v.name}: limits.max_image_pixels ({cap}) is below cameras[{i}]'s {c.settings.width}x{c.settings.height} frames; raise it"
            )
    return cap


def _camera(v: _Validator, d, key: str, base: Path) -> CameraConfig:
    if not isinstance(d, dict):
        raise ConfigError(f"{v.name}: {key} must be a table")
    v.known(
        d,
        key,
        {
            "id",
            "driver",
            "device",
            "socket",
            "path",
            "width",
            "height",
            "exposure_us",
            "iso",
            "white_balance_k",
            "focus",
            "sync",
            "fsin_discard",
        },
    )
    driver = v.choice(d, f"{key}.driver", CAMERA_DRIVERS, default="oak")
    settings = CameraSettings(
        width=v.integer(d, f"{key}.width", default=640, lo=16, hi=8192),
        height=v.integer(d, f"{key}.height", default=480, lo=16, hi=8192),
        exposure_us=v.integer(d, f"{key}.exposure_us", default=None, lo=1, hi=1_000_000),
        iso=v.integer(d, f"{key}.iso", default=None, lo=50, hi=6400),
        white_balance_k=v.integer(d, f"{key}.white_balance_k", default=None, lo=1000, hi=12000),
        focus=v.integer(d, f"{key}.focus", default=None, lo=0, hi=255),
        sync=v.choice(d, f"{key}.sync", ("software", "fsin"), default="software"),
    )
    if settings.sync == "fsin" and not settings.locked:
        raise ConfigError(
            f"{v.name}: {key}.sync = 'fsin' needs exposure_us, iso and white_balance_k (auto exposure cannot converge in snapshot mode)"
        )
    device = v.string(d, f"{key}.device", default="")
    if driver == "oak" and not device:
        raise ConfigError(f"{v.name}: {key}.device is required for an OAK camera (its device id; see `cadsplat rig list`)")
    fsin_discard = v.integer(d, f"{key}.fsin_discard", default=0, lo=0, hi=8)
    if fsin_discard and (driver != "oak" or settings.sync != "fsin"):
        raise ConfigError(f"{v.name}: {key}.fsin_discard only applies to an OAK camera with sync = 'fsin'")
    path = v.string(d, f"{key}.path", default="")
    if driver == "replay" and not path:
        raise ConfigError(f"{v.name}: {key}.path is required for a replay camera (a capture or a directory of captures)")
    return CameraConfig(
        id=v.string(d, f"{key}.id", required=True, pattern=r"[A-Za-z0-9_.-]+"),
        driver=driver,
        settings=settings,
        device=device,
        socket=v.string(d, f"{key}.socket", default="CAM_A", pattern=r"CAM_[A-J]"),
        path=str(base / path) if path else "",
        fsin_discard=fsin_discard,
    )


def _trigger(v: _Validator, d: dict) -> TriggerConfig:
    v.known(d, "trigger", set(TriggerConfig.__dataclass_fields__))
    kind = v.choice(d, "trigger.kind", TRIGGER_KINDS, default="software")
    pattern = v.string(d, "trigger.pattern", default=DEFAULT_SERIAL_PATTERN)
    try:
        if "seq" not in re.compile(pattern).groupindex:
            raise ConfigError(f"{v.name}: trigger.pattern needs a named group (?P<seq>...)")
    except re.error as e:
        raise ConfigError(f"{v.name}: trigger.pattern is not a valid regular expression ({e})") from None
    fmt = v.string(d, "trigger.payload_format", default=DEFAULT_CAN_FORMAT)
    try:
        if struct.calcsize(fmt) > 8:
            raise ConfigError(f"{v.name}: trigger.payload_format needs {struct.calcsize(fmt)} bytes; a CAN frame holds 8")
    except struct.error:
        raise ConfigError(f"{v.name}: trigger.payload_format '{fmt}' is not a struct format (e.g. '<Ii')") from None
    port = v.string(d, "trigger.port", default="")
    if kind == "serial" and not port:
        raise ConfigError(f"{v.name}: trigger.port is required for a serial trigger (e.g. /dev/ttyUSB0 or socket://host:port)")
    return TriggerConfig(
        kind=kind,
        port=port,
        baudrate=v.integer(d, "trigger.baudrate", default=115200, lo=300, hi=4_000_000),
        pattern=pattern,
        interface=v.string(d, "trigger.interface", default="socketcan"),
        channel=v.string(d, "trigger.channel", default="can0"),
        arbitration_id=v.integer(d, "trigger.arbitration_id", default=0x181, lo=0, hi=0x1FFFFFFF),
        payload_format=fmt,
        debounce_ms=v.number(d, "trigger.debounce_ms", default=5.0, lo=0.0, hi=10_000.0),
        min_interval_ms=v.number(d, "trigger.min_interval_ms", default=0.0, lo=0.0, hi=600_000.0),
    )


def _storage(v: _Validator, d: dict, base: Path) -> StorageConfig:
    v.known(d, "storage", {"root", "min_free_gb", "spill"})
    root = base / v.string(d, "storage.root", default="captures")
    spill = v.string(d, "storage.spill", default="")
    spill_dir = base / spill if spill else None
    if spill_dir is not None and Path(os.path.abspath(spill_dir)).is_relative_to(os.path.abspath(root)):
        raise ConfigError(
            f"{v.name}: storage.spill must lie outside storage.root (on another filesystem, which stays writable when the store does not)"
        )
    return StorageConfig(root=root, min_free_gb=v.number(d, "storage.min_free_gb", default=1.0, lo=0.0, hi=1e6), spill=spill_dir)


def _thresholds(v: _Validator, d: dict) -> Thresholds:
    v.known(d, "thresholds", {"sync_tolerance_ms", "black_level", "saturated_fraction", "grab_timeout_s", "max_trigger_age_s"})
    return Thresholds(
        sync_tolerance_ns=int(v.number(d, "thresholds.sync_tolerance_ms", default=5.0, lo=0.0, hi=10_000.0) * 1e6),
        black_level=v.number(d, "thresholds.black_level", default=0.02, lo=0.0, hi=1.0),
        saturated_fraction=v.number(d, "thresholds.saturated_fraction", default=0.5, lo=0.0, hi=1.0),
        grab_timeout_s=v.number(d, "thresholds.grab_timeout_s", default=2.0, lo=0.01, hi=600.0),
        max_trigger_age_ns=int(v.number(d, "thresholds.max_trigger_age_s", default=2.0, lo=0.001, hi=3600.0) * 1e9),
    )


def _inspection(v: _Validator, d: dict) -> InspectionConfig:
    v.known(d, "inspection", {"tolerance_mm", "max_unseen_pct"})
    if "tolerance_mm" not in d:
        raise ConfigError(f"{v.name}: inspection.tolerance_mm is required to inspect twins (or leave [inspection] out)")
    unseen = v.number(d, "inspection.max_unseen_pct", default=0.0, lo=0.0, hi=100.0) if "max_unseen_pct" in d else None
    return InspectionConfig(v.number(d, "inspection.tolerance_mm", default=0.0, lo=1e-6, hi=1e4), unseen)


class _Validator:
    """Typed getters whose errors name the file and the key."""

    def __init__(self, name: str) -> None:
        self.name = name

    def known(self, d: dict, where: str, keys: set[str]) -> None:
        unknown = sorted(set(d) - keys)
        if unknown:
            key = f"{where}.{unknown[0]}" if where else unknown[0]
            raise ConfigError(f"{self.name}: unknown key {key} (known: {', '.join(sorted(keys))})")

    def table(self, d: dict, key: str) -> dict:
        t = d.get(key, {})
        if not isinstance(t, dict):
            raise ConfigError(f"{self.name}: {key} must be a table ([{key}])")
        return t

    def _get(self, d: dict, key: str):
        return d.get(key.rsplit(".", 1)[-1])

    def string(self, d: dict, key: str, *, default: str = "", required: bool = False, pattern: str | None = None) -> str:
        val = self._get(d, key)
        if val is None:
            if required:
                raise ConfigError(f"{self.name}: {key} is required")
            return default
        if not isinstance(val, str) or (pattern and not re.fullmatch(pattern, val)):
            raise ConfigError(f"{self.name}: {key} must be a string{f' matching {pattern}' if pattern else ''}, got {val!r}")
        return val

    def choice(self, d: dict, key: str, options: tuple[str, ...], *, default: str) -> str:
        val = self._get(d, key)
        if val is None:
            return default
        if val not in options:
            raise ConfigError(f"{self.name}: {key} must be one of {', '.join(options)}, got {val!r}")
        return val

    def integer(self, d: dict, key: str, *, default, lo: int, hi: int):
        val = self._get(d, key)
        if val is None:
            return default
        if isinstance(val, bool) or not isinstance(val, int) or not lo <= val <= hi:
            raise ConfigError(f"{self.name}: {key} must be an integer in [{lo}, {hi}], got {val!r}")
        return val

    def number(self, d: dict, key: str, *, default: float, lo: float, hi: float) -> float:
        val = self._get(d, key)
        if val is None:
            return default
        if isinstance(val, bool) or not isinstance(val, (int, float)) or not lo <= val <= hi:
            raise ConfigError(f"{self.name}: {key} must be a number in [{lo:g}, {hi:g}], got {val!r}")
        return float(val)

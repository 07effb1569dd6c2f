"""The camera driver protocol: open, configure, arm, grab, close, health.

A driver owns one physical (or simulated) camera of the rig. Acquisition talks to every camera
through this protocol only, so OAK devices, the synthetic rig and recorded captures are
interchangeable. A camera that fails raises `CameraError`; acquisition turns that into a
quarantined capture, never into a crash. rig.assembly chooses the driver a rig.toml names.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from calibration.camera import Camera


class CameraError(RuntimeError):
    """A camera that cannot deliver: disconnected, timed out, misconfigured. One plain sentence."""


@dataclass(frozen=True)
class CameraSettings:
    """What a capture locks so all views agree photometrically.

    `exposure_us`/`iso`/`white_balance_k`/`focus` None means: let the camera converge once, then
    lock what it chose. `sync` is "software" (host-timed) or "fsin" (hardware frame-sync input).
    """

    width: int = 640
    height: int = 480
    exposure_us: int | None = None
    iso: int | None = None
    white_balance_k: int | None = None
    focus: int | None = None
    sync: str = "software"

    @property
    def locked(self) -> bool:
        return None not in (self.exposure_us, self.iso, self.white_balance_k)


@dataclass(frozen=True)
class Frame:
    """One grabbed image: RGB uint8 [H, W, 3], the host-clock (monotonic) time of exposure, what the camera used."""

    camera_id: str
    image: np.ndarray
    timestamp_ns: int
    settings: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Health:
    camera_id: str
    ok: bool
    detail: str = ""
    frames: int = 0
    errors: int = 0


@runtime_checkable
class CameraDriver(Protocol):
    """One camera of the rig. `camera` is its calibrated model (intrinsics + rig-frame c2w, OpenCV)."""

    camera_id: str

    @property
    def camera(self) -> Camera: ...

    def open(self) -> None: ...

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Apply settings; returns the settings in force (auto values resolved and locked)."""
        ...

    def arm(self, seq: int) -> None:
        """Get ready to take the frame of trigger `seq` (drop stale frames, stage the scene)."""
        ...

    def grab(self, timeout_s: float) -> Frame: ...

    def close(self) -> None: ...

    def health(self) -> Health: ...

"""What the operator screen shows, as plain data: the kiosk renders it, a backend fills it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol


@dataclass(frozen=True)
class CameraStatus:
    name: str
    online: bool
    calibration: str = "—"  # OK, WARN, RECALIBRATE, or — before the first check
    drift_deg: float | None = None
    drift_px: float | None = None
    detail: str = ""  # why it is offline, from the driver (e.g. "OAK … is disconnected (X_LINK_ERROR); reconnecting …")


@dataclass(frozen=True)
class Progress:
    capture_id: str
    stage: str
    fraction: float
    eta_s: float | None = None


@dataclass(frozen=True)
class Verdict:
    capture_id: str
    model_id: str
    registration_score: float  # mean silhouette IoU of the registration, 0..1
    fit_iou: float  # twin's silhouette IoU on its views, 0..1
    grade: str  # Good / Usable / Poor
    advice: str
    preview_path: str = ""
    inspection: str = ""  # the inspection's one-line verdict (PASS/FAIL/UNCERTAIN ...) when the rig inspects parts


@dataclass(frozen=True)
class Alarm:
    key: str
    text: str  # plain words, with what to do
    acknowledged: bool = False


@dataclass(frozen=True)
class ApplianceState:
    watching: bool = False
    trigger_source: str = "software"
    last_trigger: str = "none yet"
    cameras: tuple[CameraStatus, ...] = ()
    captures: int = 0
    quarantined: int = 0
    disk_free_gb: float = 0.0
    queue: tuple[str, ...] = ()
    progress: Progress | None = None
    last_twin: Verdict | None = None
    alarms: tuple[Alarm, ...] = ()
    message: str = ""
    disk_full: str = ""  # "STOPPED: disk full ..." while the rig or the service cannot write


class ApplianceBackend(Protocol):
    def state(self) -> ApplianceState: ...
    def toggle_watch(self) -> None: ...
    def trigger(self) -> None: ...
    def rerun(self) -> None: ...
    def acknowledge(self) -> None: ...
    def take_background(self) -> None: ...
    def close(self) -> None: ...


def grade_twin(registration_score: float, fit_iou: float) -> tuple[str, str]:
    """Plain-words quality grade of a twin, with what to do about it."""
    if registration_score >= 0.85 and fit_iou >= 0.9:
        return "Good", "Twin is ready to use."
    if registration_score >= 0.7 and fit_iou >= 0.8:
        return "Usable", "Twin is usable; check the preview before release."
    return "Poor", "Twin does not match the photos: check the part and the camera views, then re-run."


def drift_alarm(camera: CameraStatus) -> Alarm | None:
    """The alarm an operator sees for a camera whose calibration drifted."""
    if camera.calibration == "RECALIBRATE":
        deg = f"{camera.drift_deg:.1f}°" if camera.drift_deg is not None else "too far"
        return Alarm(
            f"drift:{camera.name}", f"Camera {camera.name} moved {deg} — stop the line and run a calibration (cadsplat calibrate board)."
        )
    if camera.calibration == "WARN":
        deg = f"{camera.drift_deg:.1f}°" if camera.drift_deg is not None else "a little"
        return Alarm(f"drift:{camera.name}", f"Camera {camera.name} moved {deg} — run calibration check.")
    if not camera.online:
        why = f" ({camera.detail})" if camera.detail else ""
        return Alarm(
            f"offline:{camera.name}",
            f"Camera {camera.name} is not answering{why} — captures are refused until it is back; check its cable and power.",
        )
    return None

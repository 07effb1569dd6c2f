"""The calibration keeper: checks every camera against its reference, corrects small drift as a new
calibration version, raises an alarm (and flags captures) on large drift, and keeps the history.

Beside `calibration.json` it keeps `<stem>.keeper/`:
    reference/<camera>.png     the empty-rig frame of each camera (undistorted), taken at reference time
    reference.json             the camera-to-rig poses those frames were taken with
    checks/000001.json ...     one record per check (write-once)
    alarm.json                 present while a RECALIBRATE alarm stands: cameras, since, flagged captures
`assess` and `correct` are pure; `Keeper` does the file work.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import tomllib

from calibration.calibfile import CalibrationDoc, CalibrationStore, now_iso
from calibration.capture import Capture, read_image
from calibration.drift import CHEAP, DriftEstimate, camera_drift, reprojection_effect_px
from calibration.fileio import atomic_write_bytes, atomic_write_json, atomic_write_png
from calibration.so3 import geodesic_angle_deg

OK, WARN, RECALIBRATE, UNKNOWN = "OK", "WARN", "RECALIBRATE", "UNKNOWN"
_RANK = {OK: 0, UNKNOWN: 1, WARN: 2, RECALIBRATE: 3}


@dataclass(frozen=True)
class KeeperConfig:
    """Thresholds on a camera's reprojection effect (px): below warn OK, below recalibrate WARN (auto-corrected), else RECALIBRATE."""

    warn_px: float = 0.5
    recalibrate_px: float = 3.0
    translation_tol_mm: float = 2.0
    working_depth_m: float = 1.0
    auto_correct: bool = True

    @staticmethod
    def from_toml(path: str | os.PathLike) -> KeeperConfig:
        """Read the [calibration.keeper] table of a TOML file (missing keys keep their defaults)."""
        try:
            data = tomllib.loads(Path(path).read_text())
        except (OSError, tomllib.TOMLDecodeError) as e:
            raise ValueError(f"{path}: cannot read keeper config ({e})") from None
        table = data.get("calibration", {}).get("keeper", {})
        known = set(KeeperConfig.__dataclass_fields__)
        unknown = set(table) - known
        if unknown:
            raise ValueError(f"{path}: unknown keeper settings {sorted(unknown)}; known: {sorted(known)}")
        cfg = KeeperConfig(**table)
        if not 0 < cfg.warn_px < cfg.recalibrate_px:
            raise ValueError(f"{path}: need 0 < warn_px < recalibrate_px")
        return cfg


@dataclass(frozen=True)
class CameraCheck:
    status: str
    method: str | None = None
    rotation_deg: float | None = None
    translation_mm: float | None = None
    effect_px: float | None = None
    matches: int = 0
    c2r: list | None = None


@dataclass(frozen=True)
class CheckResult:
    cameras: dict[str, CameraCheck]

    @property
    def status(self) -> str:
        return max((c.status for c in self.cameras.values()), key=_RANK.__getitem__, default=UNKNOWN)

    def drifted(self, status: str) -> list[str]:
        return [n for n, c in self.cameras.items() if c.status == status]


def _classify(effect_px: float, cfg: KeeperConfig) -> str:
    if effect_px < cfg.warn_px:
        return OK
    return WARN if effect_px < cfg.recalibrate_px else RECALIBRATE


def assess(
    calibration: CalibrationDoc,
    images: dict[str, np.ndarray],
    references: dict[str, tuple[np.ndarray, np.ndarray]],
    cfg: KeeperConfig,
    *,
    mode: str = CHEAP,
) -> CheckResult:
    """Check each camera of `images` (pinhole images) against its reference.

    references[camera] = (empty-rig frame, c2r it was taken with). The estimate is absolute (a
    camera-to-rig pose); the status compares it with the calibration's current c2r.
    """
    out: dict[str, CameraCheck] = {}
    for name, image in images.items():
        if name not in calibration.cameras:
            continue
        current = calibration.cameras[name].pinhole()
        ref = references.get(name)
        at_ref = current.with_c2w(ref[1]) if ref is not None else current
        est: DriftEstimate | None = camera_drift(
            at_ref,
            image,
            reference=None if ref is None else ref[0],
            fiducials=calibration.fiducials,
            mode=mode,
            translation_tol_mm=cfg.translation_tol_mm,
        )
        if est is None:
            out[name] = CameraCheck(UNKNOWN)
            continue
        moved = est.translation_mm is not None
        effect = reprojection_effect_px(current, est.c2r, cfg.working_depth_m if moved else None)
        out[name] = CameraCheck(
            status=_classify(effect, cfg),
            method=est.method,
            rotation_deg=float(geodesic_angle_deg(current.c2w[:3, :3], est.c2r[:3, :3])),
            translation_mm=float(1000 * np.linalg.norm(est.c2r[:3, 3] - current.c2w[:3, 3])) if moved else None,
            effect_px=effect,
            matches=est.matches,
            c2r=est.c2r.tolist(),
        )
    return CheckResult(out)


def correct(calibration: CalibrationDoc, result: CheckResult) -> CalibrationDoc | None:
    """A successor calibration with the WARN cameras moved to their measured poses; None when none drifted."""
    warned = result.drifted(WARN)
    if not warned:
        return None
    cams = {n: calibration.cameras[n].with_c2w(np.array(result.cameras[n].c2r)) for n in warned}
    notes = {n: {"rotation_deg": result.cameras[n].rotation_deg, "effect_px": result.cameras[n].effect_px} for n in warned}
    return calibration.with_cameras(cams, source="drift-correction", notes={"corrected": notes})


def capture_images(capture: Capture) -> dict[str, np.ndarray]:
    """The first view of each camera in a capture (undistorted)."""
    out: dict[str, np.ndarray] = {}
    for i, f in enumerate(capture.frames):
        if f.camera_id not in out:
            out[f.camera_id] = capture.image(i)
    return out


@dataclass
class Keeper:
    """File side of the keeper for one `calibration.json`."""

    calibration_path: Path
    config: KeeperConfig = field(default_factory=KeeperConfig)

    def __post_init__(self) -> None:
        self.calibration_path = Path(self.calibration_path)
        self.store = CalibrationStore(self.calibration_path)
        self.dir = self.calibration_path.with_name(self.calibration_path.stem + ".keeper")

    # references ---------------------------------------------------------------------------
    def references(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        meta = self.dir / "reference.json"
        if not meta.exists():
            return {}
        poses = json.loads(meta.read_text())["c2r"]
        return {n: (read_image(self.dir / "reference" / f"{n}.png"), np.array(c2r)) for n, c2r in poses.items()}

    def set_reference(self, frames: dict[str, np.ndarray]) -> list[str]:
        """Store empty-rig frames (one per camera, undistorted) as the reference for the current calibration."""
        calib = self.store.load()
        (self.dir / "reference").mkdir(parents=True, exist_ok=True)
        names = [n for n in frames if n in calib.cameras]
        if not names:
            raise ValueError(f"none of the cameras {sorted(frames)} is in {self.calibration_path}")
        for n in names:
            atomic_write_png(self.dir / "reference" / f"{n}.png", frames[n])
        atomic_write_json(
            self.dir / "reference.json",
            {"calibration_version": calib.version, "created": now_iso(), "c2r": {n: calib.cameras[n].c2w for n in names}},
        )
        return names

    # checks ---------------------------------------------------------------------------------
    def history(self) -> list[dict]:
        d = self.dir / "checks"
        return [json.loads(p.read_text()) for p in sorted(d.glob("[0-9]*.json"))] if d.exists() else []

    def alarm(self) -> dict | None:
        p = self.dir / "alarm.json"
        return json.loads(p.read_text()) if p.exists() else None

    def _record(self, record: dict) -> dict:
        d = self.dir / "checks"
        d.mkdir(parents=True, exist_ok=True)
        number = 1 + max((int(p.stem) for p in d.glob("[0-9]*.json")), default=0)
        record = {"check": number, **record}
        atomic_write_json(d / f"{number:06d}.json", record)
        return record

    def check(self, images: dict[str, np.ndarray], *, capture: str = "", mode: str = CHEAP) -> dict:
        """Check, correct or alarm, record; returns the record (status, per-camera figures, action)."""
        calib = self.store.load()
        alarm = self.alarm()
        if alarm is not None and alarm.get("calibration_version") != calib.version and calib.source != "drift-correction":
            # A fresh board/SfM calibration answers the alarm: retire it, keeping the file for the record.
            os.replace(self.dir / "alarm.json", self.dir / f"alarm-resolved-{calib.version}.json")
            alarm = None
        refs = self.references()
        if not refs and calib.fiducials is None:
            self.set_reference(images)
            return self._record(
                {
                    "time": now_iso(),
                    "capture": capture,
                    "mode": mode,
                    "calibration_version": calib.version,
                    "status": OK,
                    "action": "reference set",
                    "cameras": {},
                }
            )
        result = assess(calib, images, refs, self.config, mode=mode)
        action = "none"
        status = result.status
        if status == RECALIBRATE or alarm is not None:
            alarm = alarm or {
                "since": now_iso(),
                "calibration_version": calib.version,
                "cameras": result.drifted(RECALIBRATE),
                "flagged_captures": [],
            }
            if capture:
                alarm["flagged_captures"].append(capture)
            atomic_write_json(self.dir / "alarm.json", alarm)
            action = f"alarm: recalibrate {', '.join(alarm['cameras'])}; capture flagged"
        elif status == WARN and self.config.auto_correct:
            new = correct(calib, result)
            # A correction moves poses only: the intrinsics were judged (or forced) when the calibration was
            # made, so the gate does not refuse it; whatever it finds stays recorded under notes["forced"].
            new = self.store.commit(new, force=True)
            action = f"corrected {', '.join(result.drifted(WARN))} as calibration version {new.version}"
        return self._record(
            {
                "time": now_iso(),
                "capture": capture,
                "mode": mode,
                "calibration_version": calib.version,
                "status": status,
                "action": action,
                "cameras": {n: asdict(c) for n, c in result.cameras.items()},
            }
        )


def plot_history(records: list[dict], path: str | os.PathLike, cfg: KeeperConfig) -> str:
    """PNG of each camera's reprojection effect (px) per check, with the thresholds; returns its sha256."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4), dpi=100)
    names = sorted({n for r in records for n in r.get("cameras", {})})
    for n in names:
        xs = [r["check"] for r in records if r.get("cameras", {}).get(n, {}).get("effect_px") is not None]
        ys = [r["cameras"][n]["effect_px"] for r in records if r.get("cameras", {}).get(n, {}).get("effect_px") is not None]
        ax.plot(xs, ys, marker="o", ms=3, label=n)
    ax.axhline(cfg.warn_px, color="orange", ls="--", lw=1, label="warn (auto-correct)")
    ax.axhline(cfg.recalibrate_px, color="red", ls="--", lw=1, label="recalibrate")
    for r in records:
        if r.get("action", "").startswith("corrected"):
            ax.axvline(r["check"], color="gray", lw=0.5)
    ax.set_xlabel("check")
    ax.set_ylabel("drift effect (px)")
    ax.set_yscale("symlog", linthresh=0.1)
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title("camera drift against calibration")
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png")
    plt.close(fig)

    return atomic_write_bytes(path, buf.getvalue())

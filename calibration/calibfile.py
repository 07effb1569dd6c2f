"""The calibration document (`calibration.json`) and its version store.

`calibration.json` is the current version; every version ever made also lives, never overwritten,
in `<stem>.versions/v0001.json, v0002.json, ...` beside it. The rig frame is the first camera's
frame. Intrinsics use this project's pixel convention (pixel centres at +0.5).

Per camera: name, K (3x3), dist (OpenCV order), width, height, rms_px, c2r (camera-to-rig 4x4),
per_image_rms_px, coverage (fraction of an 8x8 image grid holding detected corners), uncertainty
({intrinsics_cv_px, extrinsics_cv_rotation_deg, extrinsics_cv_translation_mm}: differences
between calibrations from two disjoint halves of the data), outlier_views, rejected_views.

`up_rig` (when the calibration saw its board lying printed face up on the conveyor, in the frame named
`conveyor` by default): {"vector": [3] unit rig-frame direction away from gravity, "source": "calibration",
"detail": which frame it was measured in}. Captures taken under the calibration carry it to the twin.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from calibration.board import board_up
from calibration.camera import Camera
from calibration.fileio import atomic_create_bytes, atomic_write_bytes, json_default
from calibration.multiview import RigCalibration
from calibration.units import UNIT_TO_M

FORMAT = "cadsplat.calibration/1"
# The board frame (image file name, matched across cameras) taken with the board lying face up on the conveyor.
CONVEYOR_FRAME = "conveyor"


class CalibrationFileError(ValueError):
    """A calibration file that cannot be read or a version that cannot be written."""


@dataclass(frozen=True)
class QualityGate:
    """What a calibration must satisfy to be stored: reprojection RMS, principal point near the image
    centre, focal length of a real lens, and board corners over enough of the image."""

    max_rms_px: float = 2.0
    max_principal_offset: float = 0.25  # |cx - w/2| / w and |cy - h/2| / h
    focal_range: tuple[float, float] = (0.2, 20.0)  # fx, fy in units of the image's larger side
    min_coverage: float = 0.15


def quality_problems(doc: CalibrationDoc, gate: QualityGate = QualityGate()) -> list[str]:
    """One sentence per camera figure that makes `doc` implausible (empty list: it passes the gate)."""
    out = []
    for name, cam in doc.cameras.items():
        fig = doc.figures.get(name, {})
        w, h = cam.width, cam.height
        fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
        rms = fig.get("rms_px")
        if rms is not None and not float(rms) <= gate.max_rms_px:
            out.append(
                f"camera '{name}' reprojects with RMS {float(rms):.1f} px, above the {gate.max_rms_px:g} px a good calibration stays under"
            )
        if not (abs(cx - w / 2) <= gate.max_principal_offset * w and abs(cy - h / 2) <= gate.max_principal_offset * h):
            out.append(f"camera '{name}' has its principal point at ({cx:.0f}, {cy:.0f}) px, far from the centre of its {w}x{h} image")
        lo, hi = (f * max(w, h) for f in gate.focal_range)
        if not (lo <= fx <= hi and lo <= fy <= hi):
            out.append(f"camera '{name}' has focal lengths fx {fx:.0f} / fy {fy:.0f} px, outside {lo:.0f}..{hi:.0f} px for a {w}x{h} image")
        cov = fig.get("coverage")
        if cov is not None and float(cov) < gate.min_coverage:
            out.append(
                f"camera '{name}' saw board corners on only {100 * float(cov):.0f}% of its image (at least {100 * gate.min_coverage:.0f}% is needed)"
            )
    return out


@dataclass(frozen=True)
class CalibrationDoc:
    """Cameras (c2w = camera-to-rig) plus provenance and quality figures per camera."""

    cameras: dict[str, Camera]
    figures: dict[str, dict] = field(default_factory=dict)
    source: str = "board"
    board: str | None = None
    version: int | None = None
    parent: int | None = None
    created: str = ""
    notes: dict = field(default_factory=dict)
    fiducials: dict | None = None
    # "m" when the rig frame is metric; None when its scale is unknown (an SfM calibration). A board
    # calibration measures the board's squares, so it is metric unless said otherwise.
    units: str | None = None
    # The rig's up measured from the board lying on the conveyor ({"vector", "source", "detail"}); None when unmeasured.
    up_rig: dict | None = None

    def __post_init__(self) -> None:
        if self.units is None and self.source == "board":
            object.__setattr__(self, "units", "m")

    def camera(self, name: str) -> Camera:
        if name not in self.cameras:
            raise CalibrationFileError(f"calibration has no camera '{name}' (it has {', '.join(self.cameras)})")
        return self.cameras[name]

    def with_cameras(self, cameras: dict[str, Camera], *, source: str, notes: dict | None = None) -> CalibrationDoc:
        """A successor document: new poses, the same figures, this version as parent."""
        return replace(
            self, cameras={**self.cameras, **cameras}, source=source, parent=self.version, version=None, created="", notes=notes or {}
        )


def extrinsics_uncertainty(doc: CalibrationDoc) -> dict | None:
    """The worst camera's stated extrinsic uncertainty, {"rotation_deg", "translation_mm"}; None when no
    camera states one (a calibration made without the two-halves cross-check, or a hand-made file)."""
    rot, mm = [], []
    for fig in doc.figures.values():
        u = fig.get("uncertainty") or {}
        if u.get("extrinsics_cv_rotation_deg") is not None:
            rot.append(float(u["extrinsics_cv_rotation_deg"]))
        if u.get("extrinsics_cv_translation_mm") is not None:
            mm.append(float(u["extrinsics_cv_translation_mm"]))
    if not rot and not mm:
        return None
    return {"rotation_deg": max(rot, default=0.0), "translation_mm": max(mm, default=0.0)}


def now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def conveyor_up(rig: RigCalibration, frame: str) -> dict:
    """The rig's up (`up_rig`) from the board pose of frame `frame`, where the board lay face up on the conveyor;
    CalibrationFileError when the calibration solved no board pose for that frame."""
    if frame not in rig.board_to_rig:
        raise CalibrationFileError(
            f"no camera saw a usable board in frame '{frame}', the one said to show the board lying on the conveyor; "
            "the rig's up is measured from it"
        )
    vector = board_up(rig.board_to_rig[frame])
    return {"vector": [float(x) for x in vector], "source": "calibration", "detail": f"board frame '{frame}' lying face up on the conveyor"}


def from_rig(rig: RigCalibration, *, board: str | None, source: str = "board", conveyor_frame: str | None = None) -> CalibrationDoc:
    """The document of `rig`; its `up_rig` from `conveyor_frame` (which must have been solved), else from the frame
    named CONVEYOR_FRAME when there is one, else none."""
    if conveyor_frame is None and CONVEYOR_FRAME in rig.board_to_rig:
        conveyor_frame = CONVEYOR_FRAME
    up = conveyor_up(rig, conveyor_frame) if conveyor_frame is not None else None
    figures = {}
    for n in rig.cameras:
        cv = (rig.extrinsics_cv or {}).get(n, {})
        figures[n] = {
            "rms_px": rig.rms_px[n],
            "per_image_rms_px": rig.per_image_rms_px[n],
            "coverage": rig.coverage[n],
            "uncertainty": {
                "intrinsics_cv_px": rig.intrinsics_cv_px[n],
                "extrinsics_cv_rotation_deg": cv.get("rotation_deg"),
                "extrinsics_cv_translation_mm": cv.get("translation_mm"),
            },
            "outlier_views": list(rig.outliers[n]),
            "rejected_views": rig.rejected[n],
        }
    return CalibrationDoc(rig.cameras, figures, source, board, notes={"single_camera_frames": list(rig.single_camera_frames)}, up_rig=up)


def to_document(doc: CalibrationDoc) -> dict:
    cams = []
    for name, cam in doc.cameras.items():
        fig = doc.figures.get(name, {})
        cams.append(
            {
                "name": name,
                "K": cam.K.tolist(),
                "dist": cam.dist.tolist(),
                "width": cam.width,
                "height": cam.height,
                "rms_px": fig.get("rms_px"),
                "c2r": cam.c2w.tolist(),
                **{k: v for k, v in fig.items() if k != "rms_px"},
            }
        )
    out = {
        "format": FORMAT,
        "version": doc.version,
        "parent": doc.parent,
        "created": doc.created,
        "source": doc.source,
        "board": doc.board,
        "rig_frame": f"camera '{next(iter(doc.cameras))}'" if doc.cameras else None,
        "cameras": cams,
        "notes": doc.notes,
    }
    if doc.fiducials is not None:
        out["fiducials"] = doc.fiducials
    if doc.up_rig is not None:
        out["up_rig"] = doc.up_rig
    if doc.units is not None:
        out["units"] = doc.units
        out["scale"] = f"metric: the rig frame is in {doc.units} (measured by the calibration)"
    else:
        out["scale"] = "unknown: the calibration does not measure size, so captures under it carry no units"
    return out


def from_document(d: dict, where: str = "calibration") -> CalibrationDoc:
    if not isinstance(d, dict) or not str(d.get("format", "")).startswith("cadsplat.calibration/"):
        raise CalibrationFileError(f"{where}: not a cadsplat calibration file (no 'format: {FORMAT}')")
    cameras, figures = {}, {}
    try:
        for c in d["cameras"]:
            name = str(c["name"])
            cameras[name] = Camera(np.array(c["K"]), int(c["width"]), int(c["height"]), np.array(c.get("dist", [])), np.array(c["c2r"]))
            figures[name] = {k: v for k, v in c.items() if k not in ("name", "K", "dist", "width", "height", "c2r")}
    except (KeyError, TypeError, ValueError) as e:
        raise CalibrationFileError(f"{where}: camera entry is malformed ({e})") from None
    if not cameras:
        raise CalibrationFileError(f"{where}: lists no cameras")
    units = d.get("units")
    if units is not None and (not isinstance(units, str) or units not in UNIT_TO_M):
        # Checked here, where a calibration is loaded: captures state these units and every one would be refused later.
        raise CalibrationFileError(
            f"{where}: units {units!r} is not a unit cadsplat knows (one of {', '.join(UNIT_TO_M)}, or no units for an unknown scale)"
        )
    return CalibrationDoc(
        cameras,
        figures,
        d.get("source", "board"),
        d.get("board"),
        d.get("version"),
        d.get("parent"),
        d.get("created", ""),
        d.get("notes", {}),
        d.get("fiducials"),
        units,
        _up_rig(d.get("up_rig"), where),
    )


def _up_rig(value, where: str) -> dict | None:
    """A document's `up_rig`, checked: a unit vector of 3 finite numbers and a source; None when absent."""
    if value is None:
        return None
    vector = value.get("vector") if isinstance(value, dict) else None
    try:
        v = np.asarray(vector, np.float64)
    except (TypeError, ValueError):
        v = np.zeros(0)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or abs(float(np.linalg.norm(v)) - 1.0) > 1e-6:
        raise CalibrationFileError(f"{where}: up_rig must hold a unit 'vector' of 3 finite numbers, got {value!r}")
    return {**value, "vector": [float(x) for x in v], "source": str(value.get("source", "calibration"))}


def read_calibration(path: str | os.PathLike) -> CalibrationDoc:
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise CalibrationFileError(f"{path}: calibration file does not exist") from None
    except json.JSONDecodeError as e:
        raise CalibrationFileError(f"{path}: invalid JSON ({e.msg} at line {e.lineno})") from None
    return from_document(d, str(path))


def _encode(doc: CalibrationDoc) -> bytes:
    return (json.dumps(to_document(doc), indent=2, default=json_default, allow_nan=False) + "\n").encode()


def _write_new(path: Path, data: bytes) -> None:
    """Write a version file once: versions are never overwritten."""
    try:
        atomic_create_bytes(path, data)
    except FileExistsError:
        raise CalibrationFileError(f"{path}: version already exists; versions are never overwritten") from None


class CalibrationStore:
    """`calibration.json` (the current version) and `<stem>.versions/` (all versions, write-once)."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.versions_dir = self.path.with_name(self.path.stem + ".versions")

    def versions(self) -> list[int]:
        if not self.versions_dir.exists():
            return []
        return sorted(int(p.stem[1:]) for p in self.versions_dir.glob("v[0-9]*.json"))

    def load(self, version: int | None = None) -> CalibrationDoc:
        """The current calibration, or a given version."""
        if version is None:
            return read_calibration(self.path)
        p = self.versions_dir / f"v{version:04d}.json"
        if not p.exists():
            raise CalibrationFileError(f"{self.path}: has no version {version} (versions: {self.versions() or 'none'})")
        return read_calibration(p)

    def commit(self, doc: CalibrationDoc, *, force: bool = False, gate: QualityGate = QualityGate()) -> CalibrationDoc:
        """Store `doc` as the next version and make it current; returns it with version, parent, created set.

        A calibration that fails the quality gate is refused (CalibrationFileError, nothing written)
        unless `force`, which stores it with the problems under notes["forced"]. A current file that
        is not yet in the version store (made by hand or by an older tool) is archived first, so
        nothing is ever lost.
        """
        problems = quality_problems(doc, gate)
        if problems and not force:
            more = f" (and {len(problems) - 1} more problem{'s' * (len(problems) > 2)})" if len(problems) > 1 else ""
            raise CalibrationFileError(
                f"calibration refused and not stored: {problems[0]}{more}; check the board spec and the photos, or pass --force to store it marked as forced"
            )
        if problems:
            doc = replace(doc, notes={**doc.notes, "forced": problems})
        self.versions_dir.mkdir(parents=True, exist_ok=True)
        parent = doc.parent
        if self.path.exists():
            current = read_calibration(self.path)
            if current.version is None or current.version not in self.versions():
                current = replace(current, version=(max(self.versions(), default=0) + 1))
                _write_new(self.versions_dir / f"v{current.version:04d}.json", _encode(current))
            parent = current.version if parent is None else parent
        number = max(self.versions(), default=0) + 1
        doc = replace(doc, version=number, parent=parent, created=doc.created or now_iso())
        data = _encode(doc)
        _write_new(self.versions_dir / f"v{number:04d}.json", data)
        atomic_write_bytes(self.path, data)
        return doc

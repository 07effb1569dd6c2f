"""What a registration found, as the engine hands it on and as reg.json / registration.json record it.

`RegistrationResult` and its document (`to_dict` / `from_dict`), the `provenance` that ties a document to
its capture and library, and `check_fits`, which refuses a result for a capture it was not made from.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibration.capture import Capture, capture_fingerprint, rig_metres_per_unit
from calibration.sim3 import Sim3
from reconstruction.library import Library

# Rig-to-object scales considered when the rig's scale is unknown: six decades, any unit a
# calibration (metres, millimetres, an SfM frame normalised to the camera spread) can have.
SCALE_SEARCH = (1e-3, 1e3)
# How a registration was found: the whole library searched, the known part searched alone, or the known part
# placed about a previous part's pose (`RegistrationResult.method`).
METHODS = ("library_search", "known_part", "known_part_prior")


class RegistrationError(ValueError):
    """Masks and library that do not determine a registration (one plain sentence)."""


@dataclass
class RegistrationResult:
    model_id: str
    sim3_rig_to_object: Sim3
    per_view_iou: np.ndarray
    score: float
    alternatives: list[tuple[str, float]]
    ambiguity: dict | None
    timings_s: dict
    truncated_views: list[int] = field(default_factory=list)
    scale_observable: bool = True
    objective: float | None = None
    rig_metres_per_unit: float | None = None
    scale_band: tuple[float, float] = SCALE_SEARCH
    model_ties: list[dict] = field(default_factory=list)
    camera_poses: list[dict] = field(default_factory=list)
    method: str = "library_search"

    @property
    def part_scale_vs_cad(self) -> float | None:
        """Measured size of the part over its CAD model's: metres per rig unit / scale. None where nothing was measured:
        the rig's scale is unknown, or the views do not observe it (one view, or cameras at one centre)."""
        if self.rig_metres_per_unit is None or not self.scale_observable:
            return None
        return self.rig_metres_per_unit / self.sim3_rig_to_object.scale

    def scale_statement(self) -> str | None:
        """One sentence on the part's measured size against its CAD model; None when its size was not measured."""
        ratio = self.part_scale_vs_cad
        if ratio is None:
            return None
        pct = (ratio - 1.0) * 100
        word = "larger" if pct >= 0 else "smaller"
        return f"the part is {abs(pct):.1f} % {word} than its CAD model"

    def to_dict(self) -> dict:
        return {
            "model_id": self.model_id,
            "method": self.method,
            "sim3_rig_to_object": self.sim3_rig_to_object.to_dict(),
            "score": self.score,
            "objective": self.objective,
            "per_view_iou": self.per_view_iou.tolist(),
            "alternatives": [{"model_id": m, "score": s} for m, s in self.alternatives],
            "model_ties": self.model_ties,
            "ambiguity": self.ambiguity,
            "scale": {
                "metric": self.rig_metres_per_unit is not None,
                "rig_metres_per_unit": self.rig_metres_per_unit,
                "band": list(self.scale_band),
                "part_scale_vs_cad": self.part_scale_vs_cad,
                "statement": self.scale_statement(),
            },
            "camera_poses": self.camera_poses,
            "truncated_views": self.truncated_views,
            "scale_observable": self.scale_observable,
            "timings_s": self.timings_s,
        }

    @classmethod
    def from_dict(
        cls, doc: dict, *, capture: Capture | None = None, library: Library | None = None, where: str = "the registration"
    ) -> RegistrationResult:
        """The result `to_dict` wrote (reg.json, the service's registration.json), checked against the
        `capture` and `library` it is to be used with when given (and the `provenance` the document
        records). A malformed or mismatched document raises RegistrationError in one sentence."""
        if not isinstance(doc, dict):
            raise RegistrationError(f"{where} is not a registration document: it holds a JSON {type(doc).__name__}, not an object")
        try:
            scale = doc["scale"]
            reg = cls(
                model_id=_typed(doc["model_id"], str),
                sim3_rig_to_object=Sim3.from_dict(doc["sim3_rig_to_object"]),
                per_view_iou=np.asarray(doc["per_view_iou"], np.float64).reshape(-1),
                score=float(doc["score"]),
                alternatives=[(_typed(a["model_id"], str), float(a["score"])) for a in doc["alternatives"]],
                ambiguity=None if doc["ambiguity"] is None else _typed(doc["ambiguity"], dict),
                timings_s=_typed(doc["timings_s"], dict),
                truncated_views=[int(v) for v in doc["truncated_views"]],
                scale_observable=_typed(doc["scale_observable"], bool),
                objective=None if doc["objective"] is None else float(doc["objective"]),
                rig_metres_per_unit=None if scale["rig_metres_per_unit"] is None else float(scale["rig_metres_per_unit"]),
                scale_band=tuple(float(b) for b in scale["band"]),
                model_ties=[_typed(t, dict) for t in doc["model_ties"]],
                camera_poses=[_typed(p, dict) for p in doc["camera_poses"]],
                method=_typed(doc.get("method", "library_search"), str),
            )
        except KeyError as e:
            raise RegistrationError(f"{where} is not a registration document: it has no {e.args[0]!r}") from None
        except (TypeError, ValueError, AttributeError) as e:
            raise RegistrationError(f"{where} is not a registration document: {e}") from None
        if reg.method not in METHODS:
            raise RegistrationError(f"{where} is not a registration document: its method {reg.method!r} is none of {', '.join(METHODS)}")
        if len(reg.scale_band) != 2 or not np.all(np.isfinite(reg.per_view_iou)):
            raise RegistrationError(f"{where} is not a registration document: its scale band or per-view IoUs are malformed")
        if capture is not None:
            check_fits(reg, capture, where)
            views = [f.file_path for f in capture.frames]
            if doc.get("views", views) != views or doc.get("capture_sha256", capture_fingerprint(capture)) != capture_fingerprint(capture):
                raise RegistrationError(f"{where} was made from another capture than the one at {capture.root}")
        if library is not None:
            if reg.model_id not in library.ids:
                raise RegistrationError(f"{where} registers model {reg.model_id!r}, which is not in the library at {library.root}")
            if doc.get("model_sha256", library.entry(reg.model_id).sha256) != library.entry(reg.model_id).sha256:
                raise RegistrationError(f"{where} was made with another library: its {reg.model_id!r} is not the mesh in {library.root}")
        return reg


def provenance(capture: Capture, library: Library, model_id: str) -> dict:
    """What a registration document records beside `to_dict()` so `from_dict` can refuse it for another
    capture or library: the views' file paths, the capture's fingerprint, the model mesh's sha256."""
    return {
        "views": [f.file_path for f in capture.frames],
        "capture_sha256": capture_fingerprint(capture),
        "model_sha256": library.entry(model_id).sha256,
    }


def check_fits(reg: RegistrationResult, capture: Capture, where: str = "the registration") -> None:
    """Refuse (RegistrationError, one sentence) a registration of another number of views than `capture`
    has, or one made without the metric scale the capture states (or with one it does not)."""
    if len(reg.per_view_iou) != len(capture):
        raise RegistrationError(
            f"{where} registers {len(reg.per_view_iou)} camera views but the capture at {capture.root} has {len(capture)}"
        )
    metric = rig_metres_per_unit(capture.meta, capture.root)
    if reg.rig_metres_per_unit != metric:
        stated = "no metric scale" if reg.rig_metres_per_unit is None else f"{reg.rig_metres_per_unit:g} m per rig unit"
        raise RegistrationError(
            f"{where} was registered with {stated}, but the capture at {capture.root} states "
            + ("none" if metric is None else f"{metric:g} m per rig unit")
        )


def _typed(value, kind: type):
    if not isinstance(value, kind):
        raise TypeError(f"{value!r} is not a {kind.__name__}")
    return value

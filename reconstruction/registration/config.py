"""How a line registers its captures: `RegistrationConfig`, the one copy of its defaults.

rig.toml's `[registration]` table, the `register` command's options, the service and the kiosk all
build this one type (`RegistrationConfig.from_dict` reads the table as written), and `register_views`
takes it.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from calibration.sim3 import Sim3
from reconstruction.registration.result import RegistrationError
from reconstruction.registration.scale import SCALE_TOLERANCE


@dataclass(frozen=True)
class RegistrationConfig:
    """known_part: the library model every capture holds (a line running one part): no library search.
    scale_tolerance: the part's size tolerance against its CAD model on a metric rig (a fraction).
    prior: the rig-to-object Sim(3) of a previous registration of the known part: the search is then
        the part's yaw and position on the conveyor about that pose.
    photo_tie_break: on a near-tie between two poses, the one whose colours agree better across views wins.
    top_k, iou_threshold: library views kept per mask in the search, and the silhouette IoU they need.
    """

    known_part: str | None = None
    scale_tolerance: float = SCALE_TOLERANCE
    prior: Sim3 | None = None
    photo_tie_break: bool = True
    top_k: int = 50
    iou_threshold: float = 0.7

    def __post_init__(self) -> None:
        if self.prior is not None and self.known_part is None:
            raise RegistrationError("a registration prior needs the known part it is a pose of (registration.known_part)")
        if not 0.0 <= self.scale_tolerance < 1.0:
            raise RegistrationError(f"the scale tolerance must be in [0, 1), got {self.scale_tolerance}")

    def to_dict(self) -> dict:
        return {
            "known_part": self.known_part,
            "scale_tolerance": self.scale_tolerance,
            "prior": None if self.prior is None else self.prior.to_dict(),
            "photo_tie_break": self.photo_tie_break,
            "top_k": self.top_k,
            "iou_threshold": self.iou_threshold,
        }

    @classmethod
    def from_dict(cls, doc: dict, *, where: str = "registration") -> RegistrationConfig:
        """The config a table names (rig.toml's `[registration]`, or what `to_dict` wrote); absent keys take the
        defaults. A key that is unknown or of the wrong type raises RegistrationError naming `where`.key."""
        if not isinstance(doc, dict):
            raise RegistrationError(f"{where} must be a table, got {type(doc).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(doc) - known)
        if unknown:
            raise RegistrationError(f"unknown key {where}.{unknown[0]} (known: {', '.join(sorted(known))})")
        part = doc.get("known_part")
        if part is not None and not isinstance(part, str):
            raise RegistrationError(f"{where}.known_part must be a library model id (a string), got {part!r}")
        return cls(
            known_part=part or None,
            scale_tolerance=_number(doc, "scale_tolerance", where, cls.scale_tolerance, 0.0, 0.99),
            prior=_sim3(doc.get("prior"), f"{where}.prior"),
            photo_tie_break=_flag(doc, "photo_tie_break", where, cls.photo_tie_break),
            top_k=int(_number(doc, "top_k", where, cls.top_k, 1, 10000, integer=True)),
            iou_threshold=_number(doc, "iou_threshold", where, cls.iou_threshold, 0.0, 1.0),
        )


def _number(doc: dict, key: str, where: str, default: float, lo: float, hi: float, *, integer: bool = False) -> float:
    val = doc.get(key)
    if val is None:
        return default
    kinds = (int,) if integer else (int, float)
    if isinstance(val, bool) or not isinstance(val, kinds) or not lo <= val <= hi:
        raise RegistrationError(f"{where}.{key} must be {'an integer' if integer else 'a number'} in [{lo:g}, {hi:g}], got {val!r}")
    return float(val)


def _flag(doc: dict, key: str, where: str, default: bool) -> bool:
    val = doc.get(key, default)
    if not isinstance(val, bool):
        raise RegistrationError(f"{where}.{key} must be true or false, got {val!r}")
    return val


def _sim3(val, where: str) -> Sim3 | None:
    if val is None:
        return None
    try:
        sim = Sim3.from_dict(val)
    except (KeyError, TypeError, ValueError, AttributeError):
        raise RegistrationError(
            f"{where} must be a Sim(3) table (scale, rotation [3x3], translation [3]), as a reg.json's sim3_rig_to_object"
        ) from None
    if sim.rotation.shape != (3, 3) or sim.translation.shape != (3,) or not (sim.scale > 0 and np.all(np.isfinite(sim.matrix()))):
        raise RegistrationError(f"{where} must be a Sim(3) table (scale > 0, rotation [3x3], translation [3]) of finite numbers")
    return sim

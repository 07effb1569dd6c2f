"""Which way is up: the direction opposite gravity in a twin's object frame, and where it came from.

The object frame is the CAD model's own, and CAD models are drawn z-up or y-up (or any way) as their
makers chose, so no export may assume one. Up is, first that applies:

- the twin's record (twin.json `up_object`), made by the reconstruction from the up its capture carries
  (`capture_up`: the calibration's, else rig.toml's, below), its source kept and said to be recorded in the twin;
- "calibration": the rig's up measured by the calibration (`calibration.board.board_up`: its board lying
  face up on the conveyor), taken into the object frame by the twin's registration;
- "rig.toml": rig.toml's `[simulation] up` (the rig frame's up, e.g. [0, 0, 1]), taken likewise;
- "cad": the CAD model's declared up axis (`[simulation] cad_up_axis`, or the `--cad-up-axis` flag:
  "+y", "z", "-x", ...);
- "default": +z, the convention the library's CAD models follow, said as such in every manifest.

Exports then turn the part so that up is the target tool's up (glTF +Y, USD's upAxis, MuJoCo's +z).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

AXES = {"x": 0, "y": 1, "z": 2}


@dataclass(frozen=True)
class Up:
    """`vector` [3] unit, object frame, pointing away from gravity; `source` "calibration", "rig.toml", "cad" or
    "default"; `detail` says in words what it was read from (and whether the twin recorded it)."""

    vector: np.ndarray
    source: str
    detail: str

    def to_dict(self) -> dict:
        return {"vector": [float(x) for x in self.vector], "source": self.source, "detail": self.detail}


def unit(v, what: str = "up") -> np.ndarray:
    """`v` [3] as a finite unit vector, or ValueError naming `what`."""
    a = np.asarray(v, np.float64).reshape(-1)
    n = float(np.linalg.norm(a)) if a.shape == (3,) and np.all(np.isfinite(a)) else 0.0
    if n < 1e-12:
        raise ValueError(f"{what} must be a non-zero list of 3 finite numbers, got {v!r}")
    return a / n


def axis_vector(axis: str) -> np.ndarray:
    """ "+y", "y", "-z", ... -> the unit vector [3]; ValueError for anything else."""
    s = str(axis).strip().lower()
    sign = -1.0 if s.startswith("-") else 1.0
    name = s.lstrip("+-")
    if name not in AXES or len(s) - len(name) > 1:
        raise ValueError(f"an up axis is one of x, y, z with an optional sign (+y, -z), got {axis!r}")
    v = np.zeros(3)
    v[AXES[name]] = sign
    return v


def capture_up(calibration_up: dict | None, rig_up=None) -> dict | None:
    """The rig-frame up a capture carries to its twin (capture meta `up_rig`, {"vector" [3], "source", "detail"}):
    the calibration's measurement `calibration_up` (calibfile `up_rig`), else rig.toml's `[simulation] up` `rig_up`
    [3], else None. ValueError when `rig_up` is not a non-zero vector of 3 finite numbers."""
    if calibration_up is not None:
        return dict(calibration_up)
    if rig_up is None:
        return None
    v = unit(rig_up, "rig.toml's simulation.up")
    return {"vector": [float(x) for x in v], "source": "rig.toml", "detail": f"rig.toml's [simulation] up {list(map(float, rig_up))}"}


def resolve_up(
    *,
    twin_up: dict | None = None,
    calibration_up: np.ndarray | None = None,
    rig_up: np.ndarray | None = None,
    rotation_rig_to_object: np.ndarray | None = None,
    cad_up_axis: str | None = None,
) -> Up:
    """The object frame's up by precedence (module docstring): the twin's record `twin_up`
    ({"vector", "source", "detail"}; its source kept), the calibration's rig-frame `calibration_up` [3], rig.toml's rig-frame
    `rig_up` [3] (both turned by `rotation_rig_to_object` [3, 3], the registration's rotation), the
    CAD model's declared `cad_up_axis`, else +z."""
    if twin_up is not None:
        said = twin_up.get("detail") or twin_up.get("source") or "source unstated"
        return Up(
            unit(twin_up["vector"], "the twin's up_object"),
            str(twin_up.get("source", "twin")),
            f"recorded in twin.json by the reconstruction: {said}",
        )
    if calibration_up is not None and rotation_rig_to_object is not None:
        up = np.asarray(rotation_rig_to_object, np.float64) @ unit(calibration_up, "the calibration's up")
        return Up(unit(up), "calibration", "the calibration's board lying on the conveyor, through the twin's registration")
    if rig_up is not None and rotation_rig_to_object is not None:
        up = np.asarray(rotation_rig_to_object, np.float64) @ unit(rig_up, "rig.toml's simulation.up")
        return Up(
            unit(up), "rig.toml", f"rig.toml's simulation.up {list(map(float, rig_up))} in the rig frame, through the twin's registration"
        )
    if cad_up_axis is not None:
        return Up(axis_vector(cad_up_axis), "cad", f"the CAD model's declared up axis {cad_up_axis}")
    return Up(np.array([0.0, 0.0, 1.0]), "default", "no calibration, rig.toml or CAD declaration: the CAD convention +z assumed")


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation [3, 3] taking unit vector `a` [3] onto unit vector `b` [3]; for opposite
    vectors, the half turn about the coordinate axis most perpendicular to `a`."""
    a, b = unit(a, "a"), unit(b, "b")
    v = np.cross(a, b)
    c = float(a @ b)
    if c < -1.0 + 1e-12:
        axis = np.eye(3)[int(np.argmin(np.abs(a)))]
        axis = unit(axis - (axis @ a) * a, "axis")
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def standing(up: np.ndarray, target: str) -> np.ndarray:
    """Rotation [3, 3] that stands the object frame's `up` [3] along a tool's up axis `target`
    ("+y" for glTF, "+z" for MuJoCo); the identity when they already agree. Turning +z onto +y this
    way is glTF's usual z-up conversion, (x, y, z) -> (x, z, -y)."""
    return rotation_between(up, axis_vector(target))


def usd_up_axis(up: np.ndarray) -> str:
    """USD's upAxis ("Y" or "Z", the only two it has) nearer to `up` [3]."""
    u = unit(up)
    return "Y" if u[1] > u[2] else "Z"

"""`scene.toml`: which twins (or CAD meshes) go into a simulation, where, and under what physics.

```toml
duration = 2.0            # s
fps = 25                  # recorded and rendered frames per second
timestep = 0.001          # s
gravity = [0, 0, -9.81]   # m/s^2

[floor]
enabled = true
friction = 0.8

[camera]                  # Gaussian renders: "fixed" or "turntable" about `target`
mode = "turntable"
eye = [0.5, -0.5, 0.35]
target = [0, 0, 0.05]
width = 320
height = 240
fov_deg = 45
turns = 0.25              # turntable revolutions over the run

[[twin]]
name = "board"            # unique body name (default: the source's name)
path = "twins/board"      # a twin directory, or a mesh file (.obj .stl .ply .glb) with `unit`
pos = [0, 0, 0]           # object-frame origin in the world (m)
euler_deg = [0, 0, 0]     # xyz extrinsic; or quat = [w, x, y, z]
bottom = 0.0              # optional: lift so the lowest point is this high (overrides pos z)
material = "plastic"      # or density = 1050 (kg/m^3)
collision_tolerance = 0.1    # volume error allowed for the collision shapes
fixed = false             # a fixture welded to the world
```
Paths are relative to the scene file. Sizes that drive memory or run time are bounded (`BOUNDS`, and the
rendered frames `MAX_FRAME_PIXELS`); a scene past one is refused in one sentence naming the key.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tomllib

from calibration.so3 import axis_angle_to_matrix, matrix_to_quat, quat_to_matrix
from simulation.mjcf import ContactParams, SimOptions

_TOP_KEYS = {"duration", "fps", "timestep", "gravity", "floor", "camera", "twin"}
_TWIN_KEYS = {"name", "path", "unit", "pos", "euler_deg", "quat", "bottom", "material", "density", "collision_tolerance", "fixed", "splats"}
_CAMERA_KEYS = {"mode", "eye", "target", "up", "width", "height", "fov_deg", "turns"}
_FLOOR_KEYS = {"enabled", "friction", "size"}

# Upper bounds of the values that size an allocation or a loop, each with what it sizes.
BOUNDS: dict[str, tuple[float, str]] = {
    "duration": (600.0, "s; ten minutes of simulated time"),
    "fps": (240.0, "frames per second"),
    "timestep": (0.1, "s"),
    "splats": (1_000_000, "splats per twin, each sampled and rendered every frame"),
    "camera width": (4096, "pixels"),
    "camera height": (4096, "pixels"),
    "floor size": (1000.0, "m"),
}
MIN_TIMESTEP = 1e-5  # s
MAX_PHYSICS_STEPS = 10_000_000  # duration / timestep
MAX_TWINS = 100
# Every rendered frame (uint8 RGB) is held for the video: frames x width x height pixels, 1.5 GB of them.
MAX_FRAME_PIXELS = 500_000_000


@dataclass(frozen=True)
class CameraSpec:
    """The render camera: `mode` fixed or turntable (orbiting `target` about +z by `turns` revolutions
    over the run), OpenCV look-at from `eye`, image size and horizontal field of view in degrees."""

    mode: str = "turntable"
    eye: tuple[float, float, float] = (0.5, -0.5, 0.35)
    target: tuple[float, float, float] = (0.0, 0.0, 0.05)
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    width: int = 320
    height: int = 240
    fov_deg: float = 45.0
    turns: float = 0.25


@dataclass(frozen=True)
class Placement:
    """One body of the scene: its source (twin dir or mesh file), initial pose and physics."""

    name: str
    source: Path
    unit: str | None = None
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    bottom: float | None = None
    material: str | None = None
    density: float | None = None
    collision_tolerance: float = 0.1
    fixed: bool = False
    splats: int = 20000


@dataclass(frozen=True)
class Scene:
    placements: list[Placement]
    options: SimOptions
    duration: float = 2.0
    fps: float = 25.0
    camera: CameraSpec = field(default_factory=CameraSpec)


class SceneError(ValueError):
    """A scene file that cannot be used; the message names the key and the problem."""


def _vec(value, n: int, key: str) -> tuple[float, ...]:
    try:
        v = tuple(float(x) for x in value)
    except (TypeError, ValueError):
        raise SceneError(f"{key} must be a list of {n} numbers, got {value!r}") from None
    if len(v) != n or not all(math.isfinite(x) for x in v):
        raise SceneError(f"{key} must be a list of {n} finite numbers, got {value!r}")
    return v


def _positive(value, key: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise SceneError(f"{key} must be a number, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise SceneError(f"{key} must be a positive number, got {value!r}")
    return v


def _bounded(value, key: str, *, integer: bool = False) -> float:
    """A positive number no larger than its bound in BOUNDS (`key`'s last word names the bound, e.g. "twin #2 splats")."""
    if integer and (isinstance(value, bool) or not isinstance(value, int)):
        raise SceneError(f"{key} must be a whole number, got {value!r}")
    v = _positive(value, key)
    hi, what = BOUNDS[key if key in BOUNDS else key.rsplit(" ", 1)[-1]]
    if v > hi:
        raise SceneError(f"{key} must be at most {hi:.15g} ({what}), got {value!r}")
    return v


def _unknown(doc: dict, allowed: set[str], where: str) -> None:
    extra = sorted(set(doc) - allowed)
    if extra:
        raise SceneError(f"unknown key {extra[0]!r} in {where}; allowed: {', '.join(sorted(allowed))}")


def euler_xyz_to_quat(degrees: tuple[float, float, float]) -> np.ndarray:
    """Extrinsic x-then-y-then-z rotation (degrees) -> quaternion wxyz."""
    rx, ry, rz = (axis_angle_to_matrix(np.eye(3)[i] * np.deg2rad(a)) for i, a in enumerate(degrees))
    return matrix_to_quat(rz @ ry @ rx)


def _placement(doc: dict, i: int, base: Path) -> Placement:
    where = f"twin #{i + 1}"
    _unknown(doc, _TWIN_KEYS, where)
    if "path" not in doc:
        raise SceneError(f"{where} has no path (a twin directory or a mesh file)")
    source = (base / str(doc["path"])).resolve()
    if not source.exists():
        raise SceneError(f"{where}: {source} does not exist")
    if "quat" in doc and "euler_deg" in doc:
        raise SceneError(f"{where} gives both quat and euler_deg; give one orientation")
    if "quat" in doc:
        q = np.array(_vec(doc["quat"], 4, f"{where} quat"))
        if np.linalg.norm(q) < 1e-9:
            raise SceneError(f"{where} quat must not be zero")
        quat = q / np.linalg.norm(q)
    else:
        quat = euler_xyz_to_quat(_vec(doc.get("euler_deg", (0, 0, 0)), 3, f"{where} euler_deg"))
    return Placement(
        name=str(doc.get("name") or source.name.split(".")[0]),
        source=source,
        unit=doc.get("unit"),
        pos=_vec(doc.get("pos", (0, 0, 0)), 3, f"{where} pos"),
        quat=tuple(float(x) for x in quat),
        bottom=None if doc.get("bottom") is None else _vec([doc["bottom"]], 1, f"{where} bottom")[0],
        material=doc.get("material"),
        density=None if doc.get("density") is None else _positive(doc["density"], f"{where} density"),
        collision_tolerance=_positive(doc.get("collision_tolerance", 0.1), f"{where} collision_tolerance"),
        fixed=bool(doc.get("fixed", False)),
        splats=int(_bounded(doc.get("splats", 20000), f"{where} splats", integer=True)),
    )


def parse_scene(doc: dict, base: Path) -> Scene:
    """A parsed scene.toml document (paths relative to `base`) -> Scene, or SceneError."""
    _unknown(doc, _TOP_KEYS, "the scene")
    twins = doc.get("twin", [])
    if not isinstance(twins, list) or not twins:
        raise SceneError("the scene has no [[twin]] entries")
    if len(twins) > MAX_TWINS:
        raise SceneError(f"the scene has {len(twins)} [[twin]] entries; at most {MAX_TWINS}")
    if not all(isinstance(t, dict) for t in twins):
        raise SceneError("each [[twin]] must be a table")
    placements = [_placement(t, i, base) for i, t in enumerate(twins)]
    names = [p.name for p in placements]
    if len(set(names)) != len(names):
        raise SceneError(f"twin names must be unique, got {', '.join(names)}")
    floor, cam = doc.get("floor", {}), doc.get("camera", {})
    if not isinstance(floor, dict) or not isinstance(cam, dict):
        raise SceneError("[floor] and [camera] must be tables")
    _unknown(floor, _FLOOR_KEYS, "[floor]")
    contact = ContactParams()
    if "friction" in floor:
        contact = ContactParams(friction=(_positive(floor["friction"], "floor friction"), *contact.friction[1:]))
    timestep = _bounded(doc.get("timestep", 0.001), "timestep")
    if timestep < MIN_TIMESTEP:
        raise SceneError(f"timestep must be at least {MIN_TIMESTEP:g} s, got {timestep!r}")
    options = SimOptions(
        timestep=timestep,
        gravity=_vec(doc.get("gravity", (0, 0, -9.81)), 3, "gravity"),
        floor=bool(floor.get("enabled", True)),
        floor_size=_bounded(floor.get("size", 5.0), "floor size"),
        contact=ContactParams(friction=contact.friction, solref=(2 * timestep, 1.0)),
    )
    _unknown(cam, _CAMERA_KEYS, "[camera]")
    mode = cam.get("mode", "turntable")
    if mode not in ("fixed", "turntable"):
        raise SceneError(f"camera mode must be fixed or turntable, got {mode!r}")
    d = CameraSpec()
    camera = CameraSpec(
        mode=mode,
        eye=_vec(cam.get("eye", d.eye), 3, "camera eye"),
        target=_vec(cam.get("target", d.target), 3, "camera target"),
        up=_vec(cam.get("up", d.up), 3, "camera up"),
        width=int(_bounded(cam.get("width", d.width), "camera width", integer=True)),
        height=int(_bounded(cam.get("height", d.height), "camera height", integer=True)),
        fov_deg=_positive(cam.get("fov_deg", d.fov_deg), "camera fov_deg"),
        turns=float(cam.get("turns", d.turns)),
    )
    if not camera.fov_deg < 180:
        raise SceneError(f"camera fov_deg must be below 180, got {camera.fov_deg}")
    duration, fps = _bounded(doc.get("duration", 2.0), "duration"), _bounded(doc.get("fps", 25), "fps")
    if duration / timestep > MAX_PHYSICS_STEPS:
        raise SceneError(
            f"duration / timestep is {duration / timestep:.3g} physics steps; at most {MAX_PHYSICS_STEPS:,} (shorten duration or raise timestep)"
        )
    frame_pixels = (math.floor(duration * fps + 1e-9) + 1) * camera.width * camera.height
    if frame_pixels > MAX_FRAME_PIXELS:
        raise SceneError(
            f"duration x fps x camera width x height is {frame_pixels:,} rendered pixels, held for the video; "
            f"at most {MAX_FRAME_PIXELS:,} (shorten duration, or lower fps or the camera size)"
        )
    return Scene(placements, options, duration, fps, camera)


def load_scene(path: str | os.PathLike) -> Scene:
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: no such scene file")
    try:
        doc = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise SceneError(f"{path}: not valid TOML ({e})") from None
    return parse_scene(doc, path.parent)


def resting_position(vertices: np.ndarray, quat: np.ndarray, pos: np.ndarray, bottom: float | None) -> np.ndarray:
    """Body position: `pos`, with z replaced so the rotated mesh's lowest vertex sits at `bottom`."""
    pos = np.asarray(pos, np.float64).copy()
    if bottom is not None:
        pos[2] = bottom - float((np.asarray(vertices) @ quat_to_matrix(np.asarray(quat)).T)[:, 2].min())
    return pos

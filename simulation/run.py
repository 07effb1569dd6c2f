"""Run a MuJoCo model and record every body's pose per frame, with energy and contact penetration."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np


class SimulationError(RuntimeError):
    """The model did not load or the physics went unstable; the message says which and when."""


@dataclass(frozen=True)
class Trajectory:
    """Recorded frames of a run: times [T] s; per body (world excluded, `body_names` [B]) positions
    pos [T, B, 3] m and orientations quat [T, B, 4] wxyz of the body (= object) frame in the world;
    kinetic and potential energy [T] J; penetration [T] m, the deepest contact at that frame
    (0 when none); peak_penetration m, the deepest contact over every physics step."""

    times: np.ndarray
    body_names: list[str]
    pos: np.ndarray
    quat: np.ndarray
    kinetic: np.ndarray
    potential: np.ndarray
    penetration: np.ndarray
    peak_penetration: float

    def pose(self, frame: int, body: int) -> np.ndarray:
        """Object-to-world [4, 4] of `body` at `frame`."""
        from calibration.so3 import quat_to_matrix

        t = np.eye(4)
        t[:3, :3] = quat_to_matrix(self.quat[frame, body])
        t[:3, 3] = self.pos[frame, body]
        return t

    def poses(self) -> np.ndarray:
        """Object-to-world transforms [T, B, 4, 4] of every body at every frame."""
        from calibration.so3 import quat_to_matrix

        out = np.zeros(self.pos.shape[:2] + (4, 4))
        out[..., :3, :3] = quat_to_matrix(self.quat)
        out[..., :3, 3] = self.pos
        out[..., 3, 3] = 1.0
        return out

    def to_dict(self) -> dict:
        return {
            "times_s": self.times,
            "bodies": {name: {"pos": self.pos[:, b], "quat_wxyz": self.quat[:, b]} for b, name in enumerate(self.body_names)},
            "kinetic_energy_j": self.kinetic,
            "potential_energy_j": self.potential,
            "penetration_m": self.penetration,
            "peak_penetration_m": self.peak_penetration,
        }


def load_model(xml_path: str | os.PathLike):
    """mujoco.MjModel from an MJCF file; a model MuJoCo rejects raises SimulationError with its reason."""
    import mujoco

    try:
        return mujoco.MjModel.from_xml_path(str(xml_path))
    except ValueError as e:
        raise SimulationError(f"{xml_path}: MuJoCo cannot load this model ({str(e).strip().splitlines()[0]})") from None


def _penetration(data) -> float:
    if data.ncon == 0:
        return 0.0
    return float(max(0.0, -np.min(data.contact.dist[: data.ncon])))


def simulate(model, duration: float, fps: float = 30.0) -> Trajectory:
    """Step `model` (mujoco.MjModel) from its initial state for `duration` seconds, recording a frame
    at t = 0 and every 1/fps seconds. Raises SimulationError when the state stops being finite."""
    import mujoco

    if not (duration > 0 and fps > 0):
        raise ValueError(f"duration and fps must be positive, got {duration} s at {fps} fps")
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    bodies = list(range(1, model.nbody))
    names = [model.body(b).name or f"body_{b}" for b in bodies]
    n_frames = int(np.floor(duration * fps + 1e-9)) + 1
    frame_times = np.arange(n_frames) / fps
    pos = np.zeros((n_frames, len(bodies), 3))
    quat = np.zeros((n_frames, len(bodies), 4))
    kinetic, potential, pen = np.zeros(n_frames), np.zeros(n_frames), np.zeros(n_frames)
    peak = 0.0
    for f, t in enumerate(frame_times):
        while data.time < t - 0.5 * model.opt.timestep:
            mujoco.mj_step(model, data)
            peak = max(peak, _penetration(data))
        if not (np.all(np.isfinite(data.qpos)) and np.all(np.isfinite(data.qvel))) or data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number:
            raise SimulationError(f"the simulation became unstable at t = {data.time:.3f} s (non-finite state)")
        mujoco.mj_energyPos(model, data)
        mujoco.mj_energyVel(model, data)
        pos[f] = data.xpos[bodies]
        quat[f] = data.xquat[bodies]
        potential[f], kinetic[f] = data.energy
        pen[f] = _penetration(data)
    return Trajectory(frame_times, names, pos, quat, kinetic, potential, pen, peak)


@dataclass(frozen=True)
class RestReport:
    """How a body ended a run: final kinetic energy (J) and its ratio to the peak, the deepest
    contact at the end and over the run (m), the lowest mesh point's height above the floor (m),
    and how far the centre of mass lies outside the support polygon of the collision geometry's
    points touching the floor (m; 0 = statically supported)."""

    final_kinetic: float
    kinetic_ratio: float
    final_penetration: float
    peak_penetration: float
    lowest_height: float
    support_margin: float


def support_distance(com_xy: np.ndarray, contact_xy: np.ndarray) -> float:
    """Distance [m] of a point [2] outside the convex hull of points [M, 2] (0 inside)."""
    from scipy.spatial import ConvexHull, QhullError

    pts = np.asarray(contact_xy, np.float64)
    p = np.asarray(com_xy, np.float64)
    try:
        hull = ConvexHull(pts)
    except (QhullError, ValueError):
        # Collinear or too few contacts: distance to the segment they span.
        centred = pts - pts.mean(0)
        direction = np.linalg.svd(centred, full_matrices=False)[2][0] if len(pts) > 1 else np.zeros(2)
        a, b = pts[np.argmin(centred @ direction)], pts[np.argmax(centred @ direction)]
        ab = b - a
        s = np.clip(np.dot(p - a, ab) / max(np.dot(ab, ab), 1e-300), 0.0, 1.0)
        return float(np.linalg.norm(p - (a + s * ab)))
    outside = hull.equations[:, :2] @ p + hull.equations[:, 2]
    if np.all(outside <= 0):
        return 0.0
    edges = pts[hull.simplices]
    ab = edges[:, 1] - edges[:, 0]
    s = np.clip(((p - edges[:, 0]) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-300), 0.0, 1.0)
    return float(np.linalg.norm(edges[:, 0] + s[:, None] * ab - p, axis=1).min())


def rest_report(
    traj: Trajectory, body: int, vertices: np.ndarray, center_of_mass: np.ndarray, support_points: np.ndarray, contact_band: float = 2e-3
) -> RestReport:
    """Rest checks for `body` at the last frame. vertices [V, 3] (the mesh) and support_points [S, 3]
    (the collision geometry's surface points) in the object frame; points within `contact_band` of
    the lowest collision point count as touching the floor."""
    pose = traj.pose(-1, body)
    world = lambda x: np.asarray(x, np.float64) @ pose[:3, :3].T + pose[:3, 3]  # noqa: E731
    support = world(support_points)
    touching = support[support[:, 2] <= support[:, 2].min() + contact_band]
    com = world(np.asarray(center_of_mass).reshape(1, 3))[0]
    return RestReport(
        final_kinetic=float(traj.kinetic[-1]),
        kinetic_ratio=float(traj.kinetic[-1] / max(traj.kinetic.max(), 1e-300)),
        final_penetration=float(traj.penetration[-1]),
        peak_penetration=float(traj.peak_penetration),
        lowest_height=float(world(vertices)[:, 2].min()),
        support_margin=support_distance(com[:2], touching[:, :2]),
    )

"""Rotations, the one home of quaternion and angle maths: quaternions (wxyz) <-> matrices, their
product, rotation vectors, projection onto SO(3), geodesic distance. Float64 numpy throughout;
scipy's Rotation does the conversions."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def project_to_so3(m: np.ndarray) -> np.ndarray:
    """Nearest rotation (Frobenius) to `m` [..., 3, 3]; raises if the nearest orthogonal matrix is a reflection."""
    u, _, vt = np.linalg.svd(np.asarray(m, dtype=np.float64))
    det = np.linalg.det(u @ vt)
    if np.any(det < 0):
        raise ValueError("matrix is a reflection (det < 0), not a rotation")
    return u @ vt


def is_rotation(r: np.ndarray, tol: float = 1e-6) -> bool:
    """True when `r` [3, 3] is orthonormal with det +1 within `tol`."""
    r = np.asarray(r, dtype=np.float64)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        return False
    return bool(np.abs(r @ r.T - np.eye(3)).max() < tol and abs(np.linalg.det(r) - 1.0) < tol)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Quaternion(s) wxyz [..., 4] (normalised here) -> rotation matrices [..., 3, 3]."""
    q = np.asarray(q, dtype=np.float64)
    return Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).as_matrix().reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] -> unit quaternions wxyz [..., 4] with w >= 0."""
    r = np.asarray(r, dtype=np.float64)
    q = Rotation.from_matrix(r.reshape(-1, 3, 3)).as_quat(canonical=True, scalar_first=True)
    return q.reshape(r.shape[:-2] + (4,))


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a (x) b of wxyz quaternions, broadcasting [..., 4]. Written out rather than
    scipy's composition, which normalises: a splat's quaternion keeps its norm when it is turned."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, np.float64), -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def axis_angle_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector(s) [..., 3] (radians) -> rotation matrices [..., 3, 3]."""
    v = np.asarray(rotvec, dtype=np.float64)
    return Rotation.from_rotvec(v.reshape(-1, 3)).as_matrix().reshape(v.shape[:-1] + (3, 3))


def geodesic_angle_deg(r_a: np.ndarray, r_b: np.ndarray) -> np.ndarray:
    """Angle in degrees of the rotation taking `r_a` to `r_b`, both [..., 3, 3]."""
    rel = np.swapaxes(np.asarray(r_a, np.float64), -1, -2) @ np.asarray(r_b, np.float64)
    cos = np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    # arccos loses precision near 0; atan2 of |sin| and cos does not.
    skew = np.stack([rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0], rel[..., 1, 0] - rel[..., 0, 1]], -1)
    sin = 0.5 * np.linalg.norm(skew, axis=-1)
    return np.degrees(np.arctan2(sin, cos))


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Shortest-arc rotation(s) [..., 3, 3] taking unit vectors `a` to `b` [..., 3]; antiparallel pairs turn about a perpendicular axis."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    w = 1.0 + np.sum(a * b, -1, keepdims=True)
    xyz = np.cross(a, b)
    anti = w[..., 0] < 1e-12
    if np.any(anti):
        # Any axis perpendicular to a works for a half-turn.
        aa = a[anti]
        helper = np.where(np.abs(aa[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
        axis = np.cross(aa, helper)
        xyz = np.array(xyz, copy=True)
        w = np.array(w, copy=True)
        xyz[anti] = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
        w[anti] = 0.0
    return quat_to_matrix(np.concatenate([w, xyz], -1))

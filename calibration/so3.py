"""Rotations: quaternions (wxyz), projection onto SO(3), geodesic distance. Float64 throughout."""

from __future__ import annotations

import numpy as np


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
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] -> unit quaternions wxyz [..., 4] with w >= 0 (Shepperd's method)."""
    r = np.asarray(r, dtype=np.float64)
    m = r.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    diag = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], 1)
    k = diag.argmax(1)
    q = np.empty((m.shape[0], 4))
    for i in range(m.shape[0]):
        a = m[i]
        if k[i] == 0:
            s = 2.0 * np.sqrt(1.0 + tr[i])
            q[i] = [s / 4, (a[2, 1] - a[1, 2]) / s, (a[0, 2] - a[2, 0]) / s, (a[1, 0] - a[0, 1]) / s]
        elif k[i] == 1:
            s = 2.0 * np.sqrt(1.0 + a[0, 0] - a[1, 1] - a[2, 2])
            q[i] = [(a[2, 1] - a[1, 2]) / s, s / 4, (a[0, 1] + a[1, 0]) / s, (a[0, 2] + a[2, 0]) / s]
        elif k[i] == 2:
            s = 2.0 * np.sqrt(1.0 + a[1, 1] - a[0, 0] - a[2, 2])
            q[i] = [(a[0, 2] - a[2, 0]) / s, (a[0, 1] + a[1, 0]) / s, s / 4, (a[1, 2] + a[2, 1]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + a[2, 2] - a[0, 0] - a[1, 1])
            q[i] = [(a[1, 0] - a[0, 1]) / s, (a[0, 2] + a[2, 0]) / s, (a[1, 2] + a[2, 1]) / s, s / 4]
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q.reshape(r.shape[:-2] + (4,))


def axis_angle_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector(s) [..., 3] (radians) -> rotation matrices [..., 3, 3]."""
    v = np.asarray(rotvec, dtype=np.float64)
    theta = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * theta
    # sin(x/2)/x written so it stays exact at 0.
    scale = np.where(theta > 1e-12, np.sin(half) / np.where(theta > 1e-12, theta, 1.0), 0.5)
    q = np.concatenate([np.cos(half), v * scale], -1)
    return quat_to_matrix(q)


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

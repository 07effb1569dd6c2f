"""One similarity transform type: x' = scale * R @ x + t (float64).

The registration of a rig to a CAD model is `sim3_rig_to_object`: x_obj = s * R @ x_rig + t.
Applied to a camera pose (camera-to-world 4x4), a Sim(3) moves the camera centre like a point
and rotates the camera's axes; the camera's intrinsics are untouched, so the image is the same.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.so3 import geodesic_angle_deg, is_rotation, project_to_so3


class DegenerateError(ValueError):
    """A point configuration that does not determine a similarity transform."""


@dataclass(frozen=True)
class Sim3:
    """x' = scale * rotation @ x + translation. `rotation` [3, 3] in SO(3), `translation` [3], `scale` > 0."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        r = np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)
        t = np.asarray(self.translation, dtype=np.float64).reshape(3)
        s = float(self.scale)
        if not (np.isfinite(s) and s > 0):
            raise ValueError(f"Sim(3) scale must be a positive finite number, got {s}")
        if not np.all(np.isfinite(t)):
            raise ValueError("Sim(3) translation has non-finite entries")
        if not is_rotation(r, tol=1e-5):
            if np.all(np.isfinite(r)) and np.linalg.det(r) < 0:
                raise ValueError("Sim(3) rotation is a reflection (det < 0)")
            raise ValueError("Sim(3) rotation is not orthonormal")
        # Re-projecting onto SO(3) keeps det(R) = +1 exactly under long chains of compositions.
        object.__setattr__(self, "rotation", project_to_so3(r))
        object.__setattr__(self, "translation", t)
        object.__setattr__(self, "scale", s)

    @staticmethod
    def identity() -> Sim3:
        return Sim3(1.0, np.eye(3), np.zeros(3))

    @staticmethod
    def from_matrix(m: np.ndarray) -> Sim3:
        """From a 4x4 [[s R, t], [0, 1]]; raises on reflections, shear or a non-affine last row."""
        m = np.asarray(m, dtype=np.float64)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise ValueError("Sim(3) matrix must be a finite 4x4")
        if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-9):
            raise ValueError("Sim(3) matrix last row must be [0, 0, 0, 1]")
        sr = m[:3, :3]
        det = np.linalg.det(sr)
        if det <= 0:
            raise ValueError("Sim(3) matrix is a reflection or singular (det <= 0)")
        s = det ** (1.0 / 3.0)
        return Sim3(s, sr / s, m[:3, 3])

    @staticmethod
    def from_dict(d: dict) -> Sim3:
        """From {"scale", "rotation" (3x3 nested list), "translation"} as written to gt.json/twin.json."""
        return Sim3(float(d["scale"]), np.array(d["rotation"], dtype=np.float64), np.array(d["translation"], dtype=np.float64))

    def to_dict(self) -> dict:
        return {"scale": self.scale, "rotation": self.rotation.tolist(), "translation": self.translation.tolist()}

    def matrix(self) -> np.ndarray:
        """4x4 [[s R, t], [0, 1]]."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def __matmul__(self, other: Sim3) -> Sim3:
        """Composition: (self @ other)(x) = self(other(x))."""
        return Sim3(
            self.scale * other.scale,
            self.rotation @ other.rotation,
            self.scale * (self.rotation @ other.translation) + self.translation,
        )

    def inverse(self) -> Sim3:
        r_inv = self.rotation.T
        return Sim3(1.0 / self.scale, r_inv, -(r_inv @ self.translation) / self.scale)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Points [..., 3] -> [..., 3]."""
        p = np.asarray(points, dtype=np.float64)
        return self.scale * (p @ self.rotation.T) + self.translation

    def apply_to_c2w(self, c2w: np.ndarray) -> np.ndarray:
        """Camera-to-world poses [..., 4, 4] (OpenCV axes) in the source frame -> poses in the target frame.

        The camera centre moves as a point; the camera's axes rotate by R and stay orthonormal.
        """
        c2w = np.asarray(c2w, dtype=np.float64)
        out = np.array(c2w, copy=True)
        out[..., :3, :3] = self.rotation @ c2w[..., :3, :3]
        out[..., :3, 3] = self.apply(c2w[..., :3, 3])
        return out

    def rotation_deg_to(self, other: Sim3) -> float:
        """Geodesic angle between the two rotations, degrees."""
        return float(geodesic_angle_deg(self.rotation, other.rotation))


def umeyama(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None, *, with_scale: bool = True) -> Sim3:
    """Weighted least-squares Sim(3) taking `src` [N, 3] onto `dst` [N, 3] (Umeyama 1991).

    Minimises sum_i w_i |dst_i - (s R src_i + t)|^2 with R in SO(3) (reflections are never returned).
    Raises DegenerateError when the points do not determine the transform: fewer than 3
    points with weight, all points (nearly) coincident, or all points on one line.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise ValueError(f"umeyama needs two [N, 3] arrays of equal shape, got {src.shape} and {dst.shape}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise ValueError("umeyama got non-finite points")
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape[0] != src.shape[0] or np.any(w < 0) or not np.all(np.isfinite(w)):
        raise ValueError("umeyama weights must be finite, non-negative, one per point")
    if np.count_nonzero(w) < 3 or w.sum() <= 0:
        raise DegenerateError(f"umeyama needs at least 3 weighted points, got {np.count_nonzero(w)}")
    w = w / w.sum()
    mu_s = w @ src
    mu_d = w @ dst
    xs = src - mu_s
    xd = dst - mu_d
    var_s = float(w @ np.sum(xs * xs, 1))
    extent = max(float(np.abs(src).max()), float(np.abs(dst).max()), 1e-300)
    sv_src = np.linalg.svd(np.sqrt(w)[:, None] * xs, compute_uv=False)
    # Relative thresholds so millimetre and kilometre inputs are judged alike.
    if var_s <= (1e-12 * extent) ** 2 or sv_src[0] <= 1e-12 * extent:
        raise DegenerateError("umeyama: all source points coincide; rotation and scale are undetermined")
    if sv_src[1] <= 1e-9 * sv_src[0]:
        raise DegenerateError("umeyama: source points are collinear; rotation about their line is undetermined")
    cov = (w[:, None] * xd).T @ xs
    u, d, vt = np.linalg.svd(cov)
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    r = u @ np.diag(sign) @ vt
    s = float((d * sign).sum() / var_s) if with_scale else 1.0
    if s <= 0:
        raise DegenerateError("umeyama: the best fit needs a reflection; the correspondences are inconsistent")
    t = mu_d - s * r @ mu_s
    return Sim3(s, r, t)

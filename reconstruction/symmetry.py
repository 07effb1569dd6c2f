"""Near-symmetries of an object's surface: rotations about its centroid that barely move the surface.

A registration that lands on such a pose places the twin's geometry (almost) as well as the true pose
does: silhouettes cannot tell the two apart, and neither can a simulator using the twin's mesh. The
evaluation protocol's "symmetric-aware" registration errors are taken modulo these transforms.

Candidates are turns about the surface's principal axes and the object frame's axes, all through the
centroid: the n-fold turns (n = 2..6), and every turn about an axis whose sampled turns all pass (a
continuous symmetry: screwdriver, bottle), plus products of accepted turns about different axes. A
turn is accepted when the mean distance from the turned surface samples to the surface is below the
tolerance (a length in object units, e.g. the rig's calibration noise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from reconstruction.splats import sample_surface

MAX_REFINE_DEG = 15.0  # how far ICP may move a candidate turn
MIN_REFINE_GAIN = 0.2  # ICP's fit replaces a turn only if it lowers the deviation by this fraction


@dataclass(frozen=True)
class NearSymmetry:
    transform: np.ndarray  # [4, 4] object frame x -> R (x - c) + c
    axis: np.ndarray  # [3] unit rotation axis
    angle_deg: float  # rotation angle of `transform`, in (0, 180]
    deviation: float  # mean closest-point distance of the turned surface, object units
    continuous: bool  # one of the sampled turns of a continuous symmetry


def rotation_about(axis: np.ndarray, angle_rad: float, center: np.ndarray) -> np.ndarray:
    """[4, 4] rotation by `angle_rad` about the line through `center` [3] along `axis` [3] (Rodrigues)."""
    k = np.asarray(axis, np.float64)
    k = k / np.linalg.norm(k)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    R = np.eye(3) + np.sin(angle_rad) * kx + (1 - np.cos(angle_rad)) * kx @ kx
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = center - R @ center
    return T


def surface_deviation(points: np.ndarray, transform: np.ndarray, tree: cKDTree) -> float:
    """Mean distance from `points` [P, 3] moved by `transform` [4, 4] to the surface sampled in `tree`."""
    moved = points @ transform[:3, :3].T + transform[:3, 3]
    return float(tree.query(moved, workers=-1)[0].mean())


def _axis(T: np.ndarray) -> np.ndarray:
    """Unit rotation axis [3] of the rotation part of T [4, 4] (stable at 180 degrees)."""
    v = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    return v / max(np.linalg.norm(v), 1e-12)


def _angle_deg(T: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1.0, 1.0))))


def surface_moments(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact area-weighted centroid [3] and second central moment [3, 3] of a triangle surface."""
    tri = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]  # [F, 3, 3]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    total = area.sum()
    centroid = (area[:, None] * tri.mean(1)).sum(0) / total
    t = tri - centroid
    s = t.sum(1)
    # ∫ x x^T dA over a triangle = A / 12 (Σ v v^T + (Σ v)(Σ v)^T)
    second = np.einsum("f,fki,fkj->ij", area, t, t) + np.einsum("f,fi,fj->ij", area, s, s)
    return centroid, second / (12.0 * total)


def candidate_axes(second_moment: np.ndarray, min_angle_deg: float = 8.0) -> np.ndarray:
    """Principal axes of a surface (eigenvectors of its second moment [3, 3]) and the frame's x, y, z,
    none within `min_angle_deg` of another: [A, 3]."""
    _, vecs = np.linalg.eigh(second_moment)
    axes: list[np.ndarray] = []
    for a in [*vecs.T, *np.eye(3)]:
        if all(abs(float(a @ b)) < np.cos(np.radians(min_angle_deg)) for b in axes):
            axes.append(a / np.linalg.norm(a))
    return np.stack(axes)


def refine_rigid(probe: np.ndarray, transform: np.ndarray, surface: np.ndarray, tree: cKDTree, iterations: int = 15) -> np.ndarray:
    """Point-to-point ICP from `transform` [4, 4]: the nearby rigid transform that best maps `probe` [P, 3]
    onto the surface points [S, 3] (indexed by `tree`). A turn that is almost a symmetry rarely is one
    about exactly the principal axis; its best local fit is the symmetry."""
    T = np.asarray(transform, np.float64).copy()
    for _ in range(iterations):
        target = surface[tree.query(probe @ T[:3, :3].T + T[:3, 3], workers=-1)[1]]
        mp, mt = probe.mean(0), target.mean(0)
        u, _, vt = np.linalg.svd((probe - mp).T @ (target - mt))
        d = np.sign(np.linalg.det(vt.T @ u.T))
        R = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, mt - R @ mp
    return T


def near_symmetries(
    vertices: np.ndarray,
    faces: np.ndarray,
    tolerance: float,
    *,
    samples: int = 20_000,
    queries: int = 2_000,
    continuous_step_deg: float = 1.0,
    seed: int = 0,
) -> list[NearSymmetry]:
    """Rigid transforms near turns about the surface centroid that move the mesh (vertices [V, 3],
    faces [F, 3]) by a mean closest-point distance below `tolerance` (object units). Identity excluded;
    [] for an asymmetric object. Discrete turns are refined by ICP to their best local fit; a continuous
    symmetry is sampled every `continuous_step_deg` about its axis.

    The measured distance has a floor of about half the spacing of `samples` surface points, so the
    tolerance should be well above sqrt(area / samples) / 2.
    """
    if not tolerance > 0:
        raise ValueError(f"symmetry tolerance must be positive, got {tolerance}")
    rng = np.random.default_rng(seed)
    surface, _, _ = sample_surface(vertices, faces, samples, rng)
    tree = cKDTree(surface)
    probe = surface[rng.choice(len(surface), size=min(queries, len(surface)), replace=False)]
    center, moment = surface_moments(vertices, faces)

    def fit(T: np.ndarray, refine: bool) -> tuple[np.ndarray, float]:
        dev = surface_deviation(probe, T, tree)
        if not refine:
            return T, dev
        refined = refine_rigid(probe, T, surface, tree)
        # ICP may slide from a poor turn back towards the identity: that is no symmetry.
        if _angle_deg(T[:3, :3].T @ refined[:3, :3]) > MAX_REFINE_DEG:
            return T, np.inf
        # An exact turn sits at the sampling floor, where ICP only chases sample noise: keep it.
        refined_dev = surface_deviation(probe, refined, tree)
        return (refined, refined_dev) if refined_dev < (1 - MIN_REFINE_GAIN) * dev else (T, dev)

    per_axis: list[list[NearSymmetry]] = []
    have_continuous = False
    for axis in candidate_axes(moment):
        coarse = [fit(rotation_about(axis, np.radians(d), center), False)[1] for d in range(10, 360, 10)]
        found: list[NearSymmetry] = []
        if max(coarse) < tolerance:
            if have_continuous:
                continue  # a second continuous axis: a sphere-like surface, on which every pose is as good
            have_continuous = True
            for d in np.arange(continuous_step_deg, 360.0, continuous_step_deg):
                T, dev = fit(rotation_about(axis, np.radians(d), center), False)
                found.append(NearSymmetry(T, _axis(T), _angle_deg(T), dev, True))
        else:
            for n in range(2, 7):
                turns = [fit(rotation_about(axis, 2 * np.pi * j / n, center), True) for j in range(1, n)]
                if max(dev for _, dev in turns) < tolerance:
                    found += [NearSymmetry(T, _axis(T), _angle_deg(T), dev, False) for T, dev in turns]
        per_axis.append(found)

    accepted = [s for group in per_axis for s in group]
    for i, first in enumerate(per_axis):
        for second in per_axis[i + 1 :]:
            for a in first:
                for b in second:
                    T, dev = fit(a.transform @ b.transform, not (a.continuous or b.continuous))
                    if dev < tolerance:
                        accepted.append(NearSymmetry(T, _axis(T), _angle_deg(T), dev, a.continuous or b.continuous))
    return _unique(accepted)


def _unique(symmetries: list[NearSymmetry], min_angle_deg: float = 0.5) -> list[NearSymmetry]:
    """Drops the identity and transforms within `min_angle_deg` of an earlier one (same rotation twice)."""
    out: list[NearSymmetry] = []
    for s in symmetries:
        if s.angle_deg < min_angle_deg:
            continue
        if any(_angle_deg(t.transform[:3, :3].T @ s.transform[:3, :3]) < min_angle_deg for t in out):
            continue
        out.append(s)
    return out

"""Rig calibration: intrinsics of every camera and camera-to-rig poses from synchronized board views.

Initialisation chains per-view board poses (cv2.calibrateCamera) through a spanning tree of cameras
that saw the same board frame; a joint bundle adjustment (Levenberg-Marquardt on a sparse
Jacobian, Huber-weighted) then refines camera poses, board poses and, optionally, intrinsics. The rig frame is the
first camera's frame (its c2r is the identity). OpenCV 5's cv2.calibrateMultiview solves the same
problem but needs every frame to carry the same point count; ChArUco boards seen partly (occlusion,
oblique views) do not, which is the common case on a rig, so the adjustment here is our own.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import csr_matrix

from calibration.board import BoardDetection
from calibration.camera import Camera, invert_rigid
from calibration.intrinsics import (
    CalibrationError,
    IntrinsicsResult,
    calibrate_intrinsics,
    cross_validation_px,
    outlier_views,
    usable_views,
)
from calibration.so3 import axis_angle_to_matrix, geodesic_angle_deg, project_to_so3


@dataclass(frozen=True)
class RigCalibration:
    """Cameras (`c2w` = camera-to-rig) and the figures that say how good they are.

    per_image_rms_px[camera][frame], rejected[camera][frame] = reason, outliers[camera] = frame names,
    intrinsics_cv_px[camera] = cross-validation diff (px) or None, extrinsics_cv[camera] =
    {"rotation_deg", "translation_mm"} between the rigs of two disjoint halves of the frames, or None.
    """

    cameras: dict[str, Camera]
    rms_px: dict[str, float]
    per_image_rms_px: dict[str, dict[str, float]]
    coverage: dict[str, float]
    rejected: dict[str, dict[str, str]]
    outliers: dict[str, tuple[str, ...]]
    intrinsics_cv_px: dict[str, float | None]
    extrinsics_cv: dict[str, dict[str, float]] | None
    board_to_rig: dict[str, np.ndarray]
    single_camera_frames: tuple[str, ...]

    @property
    def reference(self) -> str:
        return next(iter(self.cameras))


def _rvec(r: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(r, np.float64))[0].reshape(3)


def _chordal_mean(transforms: list[np.ndarray]) -> np.ndarray:
    """Rigid mean of [4, 4] transforms: SO(3) projection of the summed rotations, median translation."""
    out = np.eye(4)
    out[:3, :3] = project_to_so3(np.sum([t[:3, :3] for t in transforms], 0))
    out[:3, 3] = np.median([t[:3, 3] for t in transforms], 0)
    return out


def _spanning_tree(names: list[str], frames_of: dict[str, set[str]]) -> dict[str, str | None]:
    """Parent of each camera reachable from names[0] through shared frames (BFS; most shared frames first)."""
    parent: dict[str, str | None] = {names[0]: None}
    queue = deque([names[0]])
    while queue:
        p = queue.popleft()
        for c in sorted(names, key=lambda c: -len(frames_of[p] & frames_of[c])):
            if c not in parent and frames_of[p] & frames_of[c]:
                parent[c] = p
                queue.append(c)
    return parent


def _distort(xy: np.ndarray, d: np.ndarray) -> np.ndarray:
    """OpenCV distortion with per-row coefficients: xy [M, 2], d [M, 5] (k1 k2 p1 p2 k3) -> [M, 2]."""
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1 + d[:, 0] * r2 + d[:, 1] * r2 * r2 + d[:, 4] * r2 * r2 * r2
    xd = x * radial + 2 * d[:, 2] * x * y + d[:, 3] * (r2 + 2 * x * x)
    yd = y * radial + d[:, 2] * (r2 + 2 * y * y) + 2 * d[:, 3] * x * y
    return np.stack([xd, yd], 1)


@dataclass(frozen=True)
class _Problem:
    cam: np.ndarray  # [M] camera index
    frame: np.ndarray  # [M] frame index
    xyz: np.ndarray  # [M, 3] board points
    uv: np.ndarray  # [M, 2] observed, OpenCV pixel convention
    num_cams: int
    num_frames: int
    refine_intrinsics: bool
    num_intr: int  # free intrinsics per camera: fx fy cx cy + the first num_dist of k1 k2 p1 p2 k3


def _unpack(p: _Problem, x: np.ndarray, intr0: np.ndarray):
    nc, nf = p.num_cams, p.num_frames
    cam = np.concatenate([np.zeros((1, 6)), x[: 6 * (nc - 1)].reshape(nc - 1, 6)])
    frm = x[6 * (nc - 1) : 6 * (nc - 1 + nf)].reshape(nf, 6)
    if p.refine_intrinsics:
        intr = np.zeros((nc, 9))
        intr[:, : p.num_intr] = x[6 * (nc - 1 + nf) :].reshape(nc, p.num_intr)
    else:
        intr = intr0
    return cam, frm, intr


def _residuals(x: np.ndarray, p: _Problem, intr0: np.ndarray) -> np.ndarray:
    cam, frm, intr = _unpack(p, x, intr0)
    r_f = axis_angle_to_matrix(frm[:, :3])
    r_c = axis_angle_to_matrix(cam[:, :3])
    x_rig = np.einsum("mij,mj->mi", r_f[p.frame], p.xyz) + frm[p.frame, 3:]
    x_cam = np.einsum("mij,mj->mi", r_c[p.cam], x_rig) + cam[p.cam, 3:]
    xy = _distort(x_cam[:, :2] / x_cam[:, 2:], intr[p.cam, 4:])
    k = intr[p.cam]
    uv = np.stack([k[:, 0] * xy[:, 0] + k[:, 2], k[:, 1] * xy[:, 1] + k[:, 3]], 1)
    return (uv - p.uv).ravel()


def _column_groups(p: _Problem) -> tuple[np.ndarray, list[np.ndarray]]:
    """Per parameter column: its finite-difference group, and the residual rows it touches.

    Columns of the same kind (say, every frame's x rotation) never share a residual row, so one
    perturbation per group differentiates all of them at once: 21 groups, whatever the rig's size.
    """
    nc, nf = p.num_cams, p.num_frames
    groups, rows = [], []
    obs = [np.flatnonzero(p.cam == c) for c in range(nc)]
    obs_f = [np.flatnonzero(p.frame == f) for f in range(nf)]

    def both(idx: np.ndarray) -> np.ndarray:
        return np.sort(np.concatenate([2 * idx, 2 * idx + 1]))

    for c in range(1, nc):
        for k in range(6):
            groups.append(k)
            rows.append(both(obs[c]))
    for f in range(nf):
        for k in range(6):
            groups.append(6 + k)
            rows.append(both(obs_f[f]))
    if p.refine_intrinsics:
        for c in range(nc):
            for k in range(p.num_intr):
                groups.append(12 + k)
                rows.append(both(obs[c]))
    return np.asarray(groups), rows


def _jacobian(x: np.ndarray, p: _Problem, intr0: np.ndarray, groups: np.ndarray, rows: list[np.ndarray]) -> csr_matrix:
    """Sparse Jacobian [2M, P] by grouped central differences (2 x 21 residual evaluations at most)."""
    data, ri, ci = [], [], []
    for g in np.unique(groups):
        cols = np.flatnonzero(groups == g)
        h = 1e-6 * np.maximum(1.0, np.abs(x[cols]))
        xp, xm = x.copy(), x.copy()
        xp[cols] += h
        xm[cols] -= h
        diff = _residuals(xp, p, intr0) - _residuals(xm, p, intr0)
        for col, step in zip(cols, h):
            r = rows[col]
            data.append(diff[r] / (2 * step))
            ri.append(r)
            ci.append(np.full(len(r), col))
    return csr_matrix((np.concatenate(data), (np.concatenate(ri), np.concatenate(ci))), shape=(2 * len(p.cam), len(x)))


def levenberg_marquardt(
    fun, jac, x0: np.ndarray, *, huber_px: float = 2.0, max_iter: int = 50, tol: float = 1e-10
) -> tuple[np.ndarray, np.ndarray]:
    """Minimise the Huber cost of residuals `fun(x)` [R] (pairs of pixel residuals) with sparse `jac(x)` [R, P].

    Normal equations on a P x P system (P is small: poses and intrinsics), IRLS weights per point.
    Returns (x, residuals).
    """

    def weights_cost(r: np.ndarray) -> tuple[np.ndarray, float]:
        n = np.sqrt(r[0::2] ** 2 + r[1::2] ** 2)
        w = np.where(n <= huber_px, 1.0, huber_px / np.maximum(n, 1e-300))
        cost = np.where(n <= huber_px, 0.5 * n * n, huber_px * (n - 0.5 * huber_px)).sum()
        return np.repeat(w, 2), float(cost)

    x = np.asarray(x0, np.float64).copy()
    r = fun(x)
    w, cost = weights_cost(r)
    lam = 1e-3
    for _ in range(max_iter):
        j = jac(x)
        jw = j.multiply(w[:, None]).tocsr()
        a = (j.T @ jw).toarray()
        g = jw.T @ r
        diag = np.diag(a).copy()
        improved = False
        while lam < 1e10:
            try:
                step = np.linalg.solve(a + lam * np.diag(np.maximum(diag, 1e-12)), -g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            x_new = x + step
            r_new = fun(x_new)
            w_new, cost_new = weights_cost(r_new)
            if np.isfinite(cost_new) and cost_new < cost:
                improved = True
                break
            lam *= 10
        if not improved:
            break
        rel = (cost - cost_new) / max(cost, 1e-300)
        x, r, w, cost = x_new, r_new, w_new, cost_new
        lam = max(lam / 10, 1e-9)
        if rel < tol or np.linalg.norm(step) < tol * (np.linalg.norm(x) + tol):
            break
    return x, r


def _intr_vector(cam: Camera) -> np.ndarray:
    d = np.zeros(5)
    d[: min(5, cam.dist.size)] = cam.dist[:5]
    return np.array([cam.K[0, 0], cam.K[1, 1], cam.K[0, 2] - 0.5, cam.K[1, 2] - 0.5, *d])


def _camera_from_vector(v: np.ndarray, size: tuple[int, int], num_dist: int, c2r: np.ndarray) -> Camera:
    k = np.array([[v[0], 0, v[2] + 0.5], [0, v[1], v[3] + 0.5], [0, 0, 1.0]])
    return Camera(k, size[0], size[1], v[4 : 4 + num_dist], c2r)


def bundle_adjust(
    views: dict[str, dict[str, BoardDetection]],
    cameras: dict[str, Camera],
    board_to_rig: dict[str, np.ndarray],
    *,
    refine_intrinsics: bool = True,
    num_dist: int = 5,
) -> tuple[dict[str, Camera], dict[str, np.ndarray], dict[str, dict[str, np.ndarray]]]:
    """Jointly refine camera-to-rig poses (first camera fixed), board poses and intrinsics.

    views[camera][frame] = detection; cameras[camera].c2w = initial c2r; board_to_rig[frame] = initial
    pose. Returns (cameras, board_to_rig, residuals[camera][frame] [N, 2] px).
    """
    names = list(cameras)
    frames = list(board_to_rig)
    ci, fi, xyz, uv = [], [], [], []
    for c, name in enumerate(names):
        for frame, det in views[name].items():
            if frame not in board_to_rig:
                continue
            ci.append(np.full(len(det), c))
            fi.append(np.full(len(det), frames.index(frame)))
            xyz.append(det.object_points)
            uv.append(det.uv - 0.5)
    if num_dist not in (0, 4, 5):
        raise ValueError(f"rig calibration supports 0, 4 or 5 distortion coefficients, got {num_dist}")
    prob = _Problem(
        np.concatenate(ci),
        np.concatenate(fi),
        np.concatenate(xyz),
        np.concatenate(uv),
        len(names),
        len(frames),
        refine_intrinsics,
        4 + num_dist,
    )
    intr0 = np.stack([_intr_vector(cameras[n]) for n in names])
    x0 = []
    for n in names[1:]:
        v = invert_rigid(cameras[n].c2w)
        x0 += [*_rvec(v[:3, :3]), *v[:3, 3]]
    for f in frames:
        x0 += [*_rvec(board_to_rig[f][:3, :3]), *board_to_rig[f][:3, 3]]
    if refine_intrinsics:
        x0 += list(intr0[:, : prob.num_intr].ravel())
    x0 = np.asarray(x0)
    groups, rows = _column_groups(prob)
    x, res = levenberg_marquardt(lambda v: _residuals(v, prob, intr0), lambda v: _jacobian(v, prob, intr0, groups, rows), x0)
    cam, frm, intr = _unpack(prob, x, intr0)
    res = res.reshape(-1, 2)
    out_cams = {}
    for c, n in enumerate(names):
        v = np.eye(4)
        v[:3, :3] = axis_angle_to_matrix(cam[c, :3])
        v[:3, 3] = cam[c, 3:]
        out_cams[n] = _camera_from_vector(intr[c], (cameras[n].width, cameras[n].height), num_dist, invert_rigid(v))
    out_frames = {}
    for j, f in enumerate(frames):
        m = np.eye(4)
        m[:3, :3] = axis_angle_to_matrix(frm[j, :3])
        m[:3, 3] = frm[j, 3:]
        out_frames[f] = m
    residuals: dict[str, dict[str, np.ndarray]] = {n: {} for n in names}
    for c, n in enumerate(names):
        for j, f in enumerate(frames):
            sel = (prob.cam == c) & (prob.frame == j)
            if sel.any():
                residuals[n][f] = res[sel]
    return out_cams, out_frames, residuals


def _initial_rig(
    names: list[str], intr: dict[str, IntrinsicsResult], views: dict[str, dict[str, BoardDetection]]
) -> tuple[dict[str, Camera], dict[str, np.ndarray]]:
    frames_of = {n: set(views[n]) for n in names}
    parent = _spanning_tree(names, frames_of)
    missing = [n for n in names if n not in parent]
    if missing:
        raise CalibrationError(
            f"camera(s) {', '.join(missing)} share no board frame with camera '{names[0]}' or the cameras linked to it; "
            "take board views that both see"
        )
    viewmat = {names[0]: np.eye(4)}
    for n in parent:  # BFS order: every parent is placed before its children
        p = parent[n]
        if p is None:
            continue
        shared = sorted(frames_of[p] & frames_of[n])
        rel = [intr[n].board_to_camera[f] @ invert_rigid(intr[p].board_to_camera[f]) for f in shared]
        viewmat[n] = _chordal_mean(rel) @ viewmat[p]
    cams = {n: intr[n].camera.with_c2w(invert_rigid(viewmat[n])) for n in names}
    board_to_rig = {}
    for f in sorted(set().union(*frames_of.values())):
        seen = [n for n in names if f in views[n]]
        best = min(seen, key=lambda n: intr[n].per_view_rms_px[f])
        board_to_rig[f] = cams[best].c2w @ intr[best].board_to_camera[f]
    return cams, board_to_rig


def _rms(r: list[np.ndarray]) -> float:
    a = np.concatenate(r)
    return float(np.sqrt(np.mean(np.sum(a * a, 1))))


def calibrate_rig(
    detections: dict[str, dict[str, BoardDetection | None]],
    image_sizes: dict[str, tuple[int, int]],
    *,
    num_dist: int = 5,
    refine_intrinsics: bool = True,
    cross_validate: bool = True,
) -> RigCalibration:
    """Calibrate a rig from detections[camera][frame] (frames matched by name across cameras).

    Raises CalibrationError naming every camera that never saw a usable board, or cameras that
    share no frame with the rest of the rig.
    """
    names = list(detections)
    if not names:
        raise CalibrationError("no cameras given")
    usable = {n: usable_views(detections[n]) for n in names}
    blind = [n for n in names if not usable[n][0]]
    if blind:
        raise CalibrationError(f"camera(s) {', '.join(blind)} never saw a usable board; check their image folders")
    intr = {n: calibrate_intrinsics(detections[n], image_sizes[n], camera_name=n, num_dist=num_dist) for n in names}
    views = {n: usable[n][0] for n in names}
    if len(names) == 1:
        cams = {names[0]: intr[names[0]].camera}
        board = dict(intr[names[0]].board_to_camera)
    else:
        cams, board = _initial_rig(names, intr, views)
    cams, board, residuals = bundle_adjust(views, cams, board, refine_intrinsics=refine_intrinsics, num_dist=num_dist)
    per_image = {n: {f: float(np.sqrt(np.mean(np.sum(r * r, 1)))) for f, r in residuals[n].items()} for n in names}
    counts: dict[str, int] = {}
    for n in names:
        for f in views[n]:
            counts[f] = counts.get(f, 0) + 1
    extr_cv = _extrinsics_cross_validation(names, views, cams, num_dist) if cross_validate and len(names) > 1 else None
    return RigCalibration(
        cameras=cams,
        rms_px={n: _rms(list(residuals[n].values())) for n in names},
        per_image_rms_px=per_image,
        coverage={n: intr[n].coverage for n in names},
        rejected={n: usable[n][1] for n in names},
        outliers={n: outlier_views(per_image[n]) for n in names},
        intrinsics_cv_px={
            n: cross_validation_px(detections[n], image_sizes[n], num_dist=num_dist) if cross_validate else None for n in names
        },
        extrinsics_cv=extr_cv,
        board_to_rig=board,
        single_camera_frames=tuple(sorted(f for f, k in counts.items() if k == 1)),
    )


def _extrinsics_cross_validation(
    names: list[str], views: dict[str, dict[str, BoardDetection]], cams: dict[str, Camera], num_dist: int
) -> dict[str, dict[str, float]] | None:
    """Rig from the even and from the odd shared frames (intrinsics held at the full solution); their per-camera difference."""
    shared = sorted(f for f in set().union(*(set(v) for v in views.values())) if sum(f in views[n] for n in names) > 1)
    rigs = []
    for half in (shared[0::2], shared[1::2]):
        sub = {n: {f: d for f, d in views[n].items() if f in half} for n in names}
        frames_of = {n: set(sub[n]) for n in names}
        if len(_spanning_tree(names, frames_of)) < len(names):
            return None
        board = {}
        viewmats = {n: invert_rigid(cams[n].c2w) for n in names}
        for f in half:
            n = next(n for n in names if f in sub[n])
            ok, rvec, tvec = cv2.solvePnP(
                sub[n][f].object_points, sub[n][f].uv - 0.5, cams[n].K - np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]]), cams[n].dist
            )
            b2c = np.eye(4)
            b2c[:3, :3] = cv2.Rodrigues(rvec)[0]
            b2c[:3, 3] = tvec.reshape(3)
            board[f] = invert_rigid(viewmats[n]) @ b2c
        rigs.append(bundle_adjust(sub, cams, board, refine_intrinsics=False, num_dist=num_dist)[0])
    return {
        n: {
            "rotation_deg": float(geodesic_angle_deg(rigs[0][n].c2w[:3, :3], rigs[1][n].c2w[:3, :3])),
            "translation_mm": float(1000 * np.linalg.norm(rigs[0][n].c2w[:3, 3] - rigs[1][n].c2w[:3, 3])),
        }
        for n in names
    }

"""Drift of one camera against its calibration: how far it turned and moved, and what that does in pixels.

Two references, best first:
- fiducials: ArUco markers fixed on the rig frame at known rig coordinates; PnP gives the camera's
  current pose outright (rotation and translation).
- background: the empty-rig frame taken at calibration time; features matched against the current
  image give the rotation (a distant, static background carries no usable translation signal;
  the object in front is rejected by RANSAC as outliers).

All functions take images and cameras and return numbers; reading and writing is the keeper's.
Images are pinhole (undistorted at load), gray or RGB, any dtype.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration.board import to_gray_u8
from calibration.camera import Camera, invert_rigid
from calibration.so3 import geodesic_angle_deg, project_to_so3

CHEAP = "cheap"
THOROUGH = "thorough"


@dataclass(frozen=True)
class DriftEstimate:
    """`c2r` is the camera's current camera-to-rig pose as measured; `effect_px` the RMS image shift it causes."""

    method: str
    rotation_deg: float
    translation_mm: float | None
    effect_px: float
    c2r: np.ndarray
    matches: int
    residual_px: float


def reprojection_effect_px(camera: Camera, c2r_new: np.ndarray, depth_m: float | None, grid: int = 12) -> float:
    """RMS pixel shift of a grid of image points at `depth_m` (None: at infinity) when the camera moves from `camera.c2w` to `c2r_new`."""
    u = (np.arange(grid) + 0.5) / grid
    uu, vv = np.meshgrid(u * camera.width, u * camera.height)
    uv = np.stack([uu.ravel(), vv.ravel()], 1)
    rays = camera.pixel_rays_camera(uv)
    if depth_m is None:
        # Directions only: rotate the rays into the new camera frame.
        rel = invert_rigid(c2r_new)[:3, :3] @ camera.c2w[:3, :3]
        moved = rays @ rel.T
        uv_new = moved[:, :2] / moved[:, 2:] @ camera.K[:2, :2].T + camera.K[:2, 2]
    else:
        world = camera.unproject(uv, np.full(len(uv), depth_m))
        uv_new, _ = camera.with_c2w(c2r_new).project(world)
    return float(np.sqrt(np.nanmean(np.sum((uv_new - uv) ** 2, 1))))


def detect_fiducials(image: np.ndarray, dictionary: str, *, refine: bool = True) -> dict[int, np.ndarray]:
    """ArUco markers in `image`: id -> corners [4, 2] (TL TR BR BL, pixel centres at +0.5)."""
    params = cv2.aruco.DetectorParameters()
    if refine:
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), params)
    corners, ids, _ = det.detectMarkers(to_gray_u8(image))
    if ids is None:
        return {}
    return {int(i): c.reshape(4, 2).astype(np.float64) + 0.5 for i, c in zip(ids.reshape(-1), corners)}


def fiducial_drift(camera: Camera, image: np.ndarray, fiducials: dict, *, mode: str = CHEAP, min_markers: int = 2) -> DriftEstimate | None:
    """Camera pose from fiducials seen in `image`; `camera.c2w` is the calibrated c2r. None when fewer than `min_markers` are seen.

    fiducials = {"dictionary", "markers": {id: [4, 3] rig-frame corners}}.
    """
    seen = detect_fiducials(image, fiducials["dictionary"], refine=True)
    markers = {int(k): np.asarray(v, np.float64) for k, v in fiducials["markers"].items()}
    ids = [i for i in seen if i in markers]
    if len(ids) < min_markers:
        return None
    obj = np.concatenate([markers[i] for i in ids])
    img = np.concatenate([seen[i] for i in ids])
    k_cv = camera.K.copy()
    k_cv[:2, 2] -= 0.5
    vm = camera.viewmat
    rvec0 = cv2.Rodrigues(vm[:3, :3])[0]
    ok, rvec, tvec = cv2.solvePnP(
        obj,
        img - 0.5,
        k_cv,
        camera.dist,
        rvec0.copy(),
        vm[:3, 3].copy().reshape(3, 1),
        useExtrinsicGuess=True,
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok:
        return None
    if mode == THOROUGH:
        rvec, tvec = cv2.solvePnPRefineLM(obj, img - 0.5, k_cv, camera.dist, rvec, tvec)
    new_vm = np.eye(4)
    new_vm[:3, :3] = cv2.Rodrigues(rvec)[0]
    new_vm[:3, 3] = tvec.reshape(3)
    c2r = invert_rigid(new_vm)
    uv, depth = camera.with_c2w(c2r).project(obj)
    residual = float(np.sqrt(np.mean(np.sum((uv - img) ** 2, 1))))
    return DriftEstimate(
        method="fiducials",
        rotation_deg=float(geodesic_angle_deg(camera.c2w[:3, :3], c2r[:3, :3])),
        translation_mm=float(1000 * np.linalg.norm(c2r[:3, 3] - camera.c2w[:3, 3])),
        effect_px=reprojection_effect_px(camera, c2r, float(np.median(depth))),
        c2r=c2r,
        matches=len(obj),
        residual_px=residual,
    )


def _features(gray: np.ndarray, mode: str):
    if mode == THOROUGH:
        f = cv2.SIFT_create(nfeatures=4000)
    else:
        f = cv2.ORB_create(nfeatures=800, fastThreshold=10)
    return f.detectAndCompute(gray, None)


def rotation_from_rays(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Least-squares rotation R [3, 3] with b ~ R a for unit rays a, b [N, 3] (Kabsch)."""
    u, _, vt = np.linalg.svd(b.T @ a)
    return u @ np.diag([1, 1, np.sign(np.linalg.det(u @ vt))]) @ vt


def background_drift(
    camera: Camera, reference: np.ndarray, image: np.ndarray, *, mode: str = CHEAP, min_matches: int = 30
) -> DriftEstimate | None:
    """Camera rotation since `reference` (its empty-rig frame at calibration) from matched features; None when too few match.

    The rotation R maps reference rays to current rays (b = R a); the camera turned by R^T.
    """
    g_ref, g_cur = to_gray_u8(reference), to_gray_u8(image)
    kp_a, des_a = _features(g_ref, mode)
    kp_b, des_b = _features(g_cur, mode)
    if des_a is None or des_b is None or len(kp_a) < min_matches or len(kp_b) < min_matches:
        return None
    norm = cv2.NORM_L2 if mode == THOROUGH else cv2.NORM_HAMMING
    pairs = cv2.BFMatcher(norm).knnMatch(des_a, des_b, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < 0.8 * p[1].distance]
    if len(good) < min_matches:
        return None
    uv_a = np.array([kp_a[m.queryIdx].pt for m in good]) + 0.5
    uv_b = np.array([kp_b[m.trainIdx].pt for m in good]) + 0.5
    # A pure rotation is the homography K R K^-1: RANSAC on it rejects the object and mismatches.
    _, inl = cv2.findHomography(uv_a, uv_b, cv2.USAC_MAGSAC, 1.0, maxIters=2000, confidence=0.999)
    if inl is None or inl.sum() < min_matches:
        return None
    inl = inl.ravel().astype(bool)
    ra = camera.pixel_rays_camera(uv_a[inl])
    rb = camera.pixel_rays_camera(uv_b[inl])
    ra /= np.linalg.norm(ra, axis=1, keepdims=True)
    rb /= np.linalg.norm(rb, axis=1, keepdims=True)
    rot = rotation_from_rays(ra, rb)
    # One re-weighted pass: drop rays more than 3 px (in angle) off the first fit.
    err = np.linalg.norm(rb - ra @ rot.T, axis=1) * camera.K[0, 0]
    keep = err < max(3 * np.median(err), 0.5)
    rot = rotation_from_rays(ra[keep], rb[keep])
    err = np.linalg.norm(rb[keep] - ra[keep] @ rot.T, axis=1) * camera.K[0, 0]
    c2r = camera.c2w.copy()
    c2r[:3, :3] = project_to_so3(camera.c2w[:3, :3] @ rot.T)
    return DriftEstimate(
        method="background",
        rotation_deg=float(geodesic_angle_deg(np.eye(3), rot)),
        translation_mm=None,
        effect_px=reprojection_effect_px(camera, c2r, None),
        c2r=c2r,
        matches=int(keep.sum()),
        residual_px=float(np.sqrt(np.mean(err**2))),
    )


def camera_drift(
    camera: Camera,
    image: np.ndarray,
    *,
    reference: np.ndarray | None = None,
    fiducials: dict | None = None,
    mode: str = CHEAP,
    translation_tol_mm: float = 2.0,
) -> DriftEstimate | None:
    """Best available drift estimate for one camera; None when it has no usable reference in this image.

    Rotation comes from the background when a reference frame exists (hundreds of features pin it
    to thousandths of a degree); fiducials give the translation, taken only beyond
    `translation_tol_mm` (PnP on a few small markers is noisy at the millimetre level), and the
    whole pose when there is no background reference.
    """
    fid = fiducial_drift(camera, image, fiducials, mode=mode) if fiducials else None
    bg = background_drift(camera, reference, image, mode=mode) if reference is not None else None
    if bg is None:
        return fid
    if fid is None or fid.translation_mm is None or fid.translation_mm <= translation_tol_mm:
        return bg
    c2r = bg.c2r.copy()
    c2r[:3, 3] = fid.c2r[:3, 3]
    depth = float(np.median(camera.with_c2w(fid.c2r).project(np.asarray(list(fiducials["markers"].values()), float).reshape(-1, 3))[1]))
    return DriftEstimate(
        method="background+fiducials",
        rotation_deg=bg.rotation_deg,
        translation_mm=fid.translation_mm,
        effect_px=reprojection_effect_px(camera, c2r, depth),
        c2r=c2r,
        matches=bg.matches + fid.matches,
        residual_px=bg.residual_px,
    )

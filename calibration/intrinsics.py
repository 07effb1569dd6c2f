"""Per-camera intrinsics from board detections, and how much to trust them.

`calibrate_intrinsics` wraps cv2.calibrateCamera (OpenCV pixel centres are integers; ours are at
+0.5, converted here). The uncertainty figure is mrcal's cross-validation idea: calibrate from two
disjoint halves of the views and measure, in pixels, how differently the two models map the image
after the best rotation between them is factored out.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from calibration.board import BoardDetection, coverage
from calibration.camera import Camera

MIN_VIEWS = 3


class CalibrationError(ValueError):
    """Board data that cannot produce a calibration; the message names the camera or view."""


@dataclass(frozen=True)
class IntrinsicsResult:
    """A camera's intrinsics (`camera.c2w` = identity), fit residuals and the board pose of each used view.

    `board_to_camera` maps view name -> [4, 4] rigid transform (board frame -> camera frame).
    """

    camera: Camera
    rms_px: float
    per_view_rms_px: dict[str, float]
    board_to_camera: dict[str, np.ndarray]
    coverage: float
    rejected: dict[str, str] = field(default_factory=dict)
    outliers: tuple[str, ...] = ()


def usable_views(detections: dict[str, BoardDetection | None]) -> tuple[dict[str, BoardDetection], dict[str, str]]:
    """Split views into usable detections and rejected view names with a reason."""
    ok: dict[str, BoardDetection] = {}
    rejected: dict[str, str] = {}
    for name, det in detections.items():
        if det is None:
            rejected[name] = "no board found (blurred, out of view or too few corners)"
        elif det.collinear:
            rejected[name] = "all detected corners are collinear"
        else:
            ok[name] = det
    return ok, rejected


def rigid_from_rvec_tvec(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3))[0]
    m[:3, 3] = np.asarray(tvec, np.float64).reshape(3)
    return m


def outlier_views(per_view_rms: dict[str, float], factor: float = 3.0, floor_px: float = 0.5) -> tuple[str, ...]:
    """Views whose RMS exceeds `factor` x the median and the median + `floor_px` (both, so clean sets flag none)."""
    if len(per_view_rms) < 3:
        return ()
    med = float(np.median(list(per_view_rms.values())))
    return tuple(n for n, r in per_view_rms.items() if r > factor * med and r > med + floor_px)


def calibrate_intrinsics(
    detections: dict[str, BoardDetection | None],
    image_size: tuple[int, int],
    *,
    camera_name: str = "camera",
    num_dist: int = 5,
    flags: int = 0,
) -> IntrinsicsResult:
    """K, distortion (`num_dist` = 0, 4, 5 or 8 OpenCV coefficients) and board poses from the views of one camera.

    `detections` maps view name -> detection (None for images without a board). Rejected views are
    reported, not fatal; fewer than MIN_VIEWS usable views raise CalibrationError naming the camera.
    """
    views, rejected = usable_views(detections)
    if len(views) < MIN_VIEWS:
        raise CalibrationError(f"camera '{camera_name}' has {len(views)} usable board views; intrinsics need at least {MIN_VIEWS}")
    names = list(views)
    obj = [views[n].object_points.astype(np.float32) for n in names]
    img = [(views[n].uv - 0.5).astype(np.float32) for n in names]
    if num_dist == 0:
        flags |= cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
    elif num_dist == 4:
        flags |= cv2.CALIB_FIX_K3
    elif num_dist == 8:
        flags |= cv2.CALIB_RATIONAL_MODEL
    elif num_dist != 5:
        raise ValueError(f"num_dist must be 0, 4, 5 or 8, got {num_dist}")
    rms, k, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, tuple(image_size), None, None, flags=flags)
    dist = dist.reshape(-1)[:num_dist]
    camera = Camera(_k_from_opencv(k), image_size[0], image_size[1], dist)
    poses = {n: rigid_from_rvec_tvec(r, t) for n, r, t in zip(names, rvecs, tvecs)}
    per_view = {n: view_rms(camera, poses[n], views[n]) for n in names}
    return IntrinsicsResult(
        camera=camera,
        rms_px=float(rms),
        per_view_rms_px=per_view,
        board_to_camera=poses,
        coverage=coverage(views.values(), image_size),
        rejected=rejected,
        outliers=outlier_views(per_view),
    )


def _k_from_opencv(k: np.ndarray) -> np.ndarray:
    out = np.array(k, dtype=np.float64)
    out[:2, 2] += 0.5
    return out


def view_rms(camera: Camera, board_to_camera: np.ndarray, det: BoardDetection) -> float:
    """RMS reprojection error (px) of one detection under `camera` (c2w ignored) and a board pose."""
    uv, _ = camera.with_c2w(np.linalg.inv(board_to_camera)).project(det.object_points)
    return float(np.sqrt(np.mean(np.sum((uv - det.uv) ** 2, 1))))


def intrinsics_diff_px(a: Camera, b: Camera, grid: int = 24) -> float:
    """RMS pixel distance between where `a` and `b` map the same rays, best rotation between them removed.

    A grid over the image is unprojected by `a`; the rotation that best aligns those rays with `b`'s
    rays for the same pixels is factored out (mrcal: the two fits may disagree on the frame), then
    the rotated rays are projected by `b`.
    """
    u = (np.arange(grid) + 0.5) / grid
    uu, vv = np.meshgrid(u * a.width, u * a.height)
    uv = np.stack([uu.ravel(), vv.ravel()], 1)
    ra = a.pixel_rays_camera(uv)
    rb = b.pixel_rays_camera(uv)
    ra /= np.linalg.norm(ra, axis=1, keepdims=True)
    rb /= np.linalg.norm(rb, axis=1, keepdims=True)
    uu_, _, vt = np.linalg.svd(rb.T @ ra)
    rot = uu_ @ np.diag([1, 1, np.sign(np.linalg.det(uu_ @ vt))]) @ vt
    uv_b, _ = b.project(ra @ rot.T)
    return float(np.sqrt(np.nanmean(np.sum((uv_b - uv) ** 2, 1))))


def cross_validation_px(
    detections: dict[str, BoardDetection | None], image_size: tuple[int, int], *, num_dist: int = 5, flags: int = 0
) -> float | None:
    """Intrinsics diff (px) between calibrations from the even and odd usable views; None below 2 x MIN_VIEWS views."""
    views, _ = usable_views(detections)
    names = sorted(views)
    if len(names) < 2 * MIN_VIEWS:
        return None
    halves = [{n: views[n] for n in names[i::2]} for i in (0, 1)]
    cams = [calibrate_intrinsics(h, image_size, num_dist=num_dist, flags=flags).camera for h in halves]
    return intrinsics_diff_px(cams[0], cams[1])

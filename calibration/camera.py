"""The one camera model: OpenCV pinhole + OpenCV distortion + image size + pose (float64).

Axes are OpenCV's (x right, y down, z forward). `c2w` is camera-to-world, `viewmat` its inverse
(world-to-camera, as in gsplat). Pixel (u, v) covers [u, u+1) x [v, v+1), so a continuous image
coordinate of the centre of pixel (0, 0) is (0.5, 0.5); K maps camera rays to these coordinates.
Distortion coefficients follow OpenCV's order: k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4]]].
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from calibration.so3 import is_rotation

# Flips y and z: OpenCV camera axes <-> OpenGL/nerfstudio camera axes (x right, y up, z back).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])
_DIST_SIZES = (0, 4, 5, 8, 12)


def c2w_opencv_to_opengl(c2w: np.ndarray) -> np.ndarray:
    """Camera-to-world [..., 4, 4] with OpenCV camera axes -> nerfstudio/OpenGL camera axes."""
    return np.asarray(c2w, dtype=np.float64) @ _CV_TO_GL


def c2w_opengl_to_opencv(c2w: np.ndarray) -> np.ndarray:
    """Camera-to-world [..., 4, 4] with nerfstudio/OpenGL camera axes -> OpenCV camera axes."""
    return np.asarray(c2w, dtype=np.float64) @ _CV_TO_GL


def invert_rigid(m: np.ndarray) -> np.ndarray:
    """Inverse of rigid 4x4 transforms [..., 4, 4] (exact, no general matrix inverse)."""
    m = np.asarray(m, dtype=np.float64)
    out = np.zeros_like(m)
    rt = np.swapaxes(m[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -(rt @ m[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply OpenCV distortion to normalised coordinates [N, 2] (x/z, y/z) -> [N, 2]."""
    d = np.zeros(12)
    d[: len(dist)] = dist
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r4
    return np.stack([xd, yd], 1)


# OpenCV's undistortion iterates until the point, distorted again, lies within 1e-15 (normalised
# units) of the input: a few dozen iterations for real lenses, as exact as float64 allows.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)


def undistort_normalized(xy_d: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Invert `distort_normalized` for [N, 2] normalised points (cv2.undistortPoints with identity K)."""
    xy_d = np.asarray(xy_d, dtype=np.float64).reshape(-1, 2)
    if not np.any(dist) or len(xy_d) == 0:
        return xy_d.copy()
    xy = cv2.undistortPoints(xy_d[:, None, :], np.eye(3), np.asarray(dist, np.float64), None, None, None, _UNDISTORT_CRITERIA)
    return xy[:, 0, :]


def project_points(
    points: np.ndarray, K: np.ndarray, viewmat: np.ndarray | None = None, dist: np.ndarray | None = None, *, near: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """The one pinhole projection: `points` [N, 3] -> pixel coordinates [N, 2] (pixel centres at +0.5)
    and camera depths z [N].

    `K` [3, 3]; `viewmat` [4, 4] world-to-camera (None: the points are in the camera frame); `dist`
    OpenCV coefficients, applied when any is non-zero. Points at depth <= `near` get uv = NaN.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cam = p if viewmat is None else p @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = cam[:, :2] / np.where(z > near, z, np.nan)[:, None]
    if dist is not None and np.any(dist):
        xy = distort_normalized(xy, dist)
    return xy @ K[:2, :2].T + K[:2, 2], z


@dataclass(frozen=True)
class Camera:
    """Intrinsics `K` [3, 3], distortion `dist` [0|4|5|8|12], image `width` x `height`, pose `c2w` [4, 4]."""

    K: np.ndarray
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(0))
    c2w: np.ndarray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self) -> None:
        k = np.asarray(self.K, dtype=np.float64)
        dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        c2w = np.asarray(self.c2w, dtype=np.float64)
        if k.shape != (3, 3) or not np.all(np.isfinite(k)):
            raise ValueError("camera K must be a finite 3x3 matrix")
        if k[0, 0] <= 0 or k[1, 1] <= 0 or not np.allclose(k[2], [0, 0, 1]) or k[1, 0] != 0:
            raise ValueError("camera K must have positive focal lengths and last row [0, 0, 1]")
        if dist.size not in _DIST_SIZES or not np.all(np.isfinite(dist)):
            raise ValueError(f"camera distortion must hold 0, 4, 5, 8 or 12 finite OpenCV coefficients, got {dist.size}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"camera image size must be positive, got {self.width}x{self.height}")
        if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
            raise ValueError("camera c2w must be a finite 4x4 matrix")
        if not is_rotation(c2w[:3, :3], tol=1e-5) or not np.allclose(c2w[3], [0, 0, 0, 1]):
            raise ValueError("camera c2w must be rigid: an orthonormal rotation with det +1 and last row [0, 0, 0, 1]")
        object.__setattr__(self, "K", k)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "c2w", c2w)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def viewmat(self) -> np.ndarray:
        """World-to-camera [4, 4]."""
        return invert_rigid(self.c2w)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates [3]."""
        return self.c2w[:3, 3].copy()

    @property
    def is_pinhole(self) -> bool:
        return not np.any(self.dist)

    def with_c2w(self, c2w: np.ndarray) -> Camera:
        return replace(self, c2w=np.asarray(c2w, dtype=np.float64))

    def pinhole(self) -> Camera:
        """The same camera with its distortion removed (what `undistort_image` produces)."""
        return replace(self, dist=np.zeros(0))

    def scaled(self, width: int, height: int) -> Camera:
        """The camera of the same view resampled to `width` x `height` pixels."""
        sx, sy = width / self.width, height / self.height
        k = self.K.copy()
        k[0] *= sx
        k[1] *= sy
        return replace(self, K=k, width=int(width), height=int(height))

    def crop(self, canvas: np.ndarray) -> np.ndarray:
        """This view's pixels [height, width, ...] of an image or mask [H, W, ...] on a canvas at least its size,
        where views of mixed sizes sit top-left (`load_views`): K needs no shift."""
        return canvas[: self.height, : self.width]

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points [N, 3] -> pixel coordinates [N, 2] (pixel centres at +0.5) and depths [N].

        Points at or behind the camera plane get uv = NaN; check `depth > 0`.
        """
        return project_points(points, self.K, self.viewmat, self.dist)

    def unproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Pixel coordinates [N, 2] and depths (camera z) [N] -> world points [N, 3]."""
        return self.pixel_rays_camera(uv) * np.asarray(depth, np.float64).reshape(-1, 1) @ self.c2w[:3, :3].T + self.c2w[:3, 3]

    def pixel_rays_camera(self, uv: np.ndarray) -> np.ndarray:
        """Pixel coordinates [N, 2] -> camera-frame rays [N, 3] with z = 1 (distortion removed)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        k_inv = np.linalg.inv(self.K)
        xy_d = uv @ k_inv[:2, :2].T + k_inv[:2, 2]
        xy = undistort_normalized(xy_d, self.dist)
        return np.concatenate([xy, np.ones((len(xy), 1))], 1)

    def to_dict(self) -> dict:
        return {
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "width": self.width,
            "height": self.height,
            "c2w": self.c2w.tolist(),
        }

    @staticmethod
    def from_dict(d: dict) -> Camera:
        return Camera(np.array(d["K"]), int(d["width"]), int(d["height"]), np.array(d.get("dist", [])), np.array(d.get("c2w", np.eye(4))))

    @staticmethod
    def from_fov(fov_x: float, width: int, height: int, c2w: np.ndarray | None = None, fov_y: float | None = None) -> Camera:
        """Pinhole camera from horizontal field of view (radians), centred principal point (Blender NeRF-synthetic)."""
        fx = 0.5 * width / np.tan(0.5 * fov_x)
        fy = fx if fov_y is None else 0.5 * height / np.tan(0.5 * fov_y)
        k = np.array([[fx, 0, width / 2], [0, fy, height / 2], [0, 0, 1.0]])
        return Camera(k, width, height, np.zeros(0), np.eye(4) if c2w is None else c2w)


def look_at_c2w(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """OpenCV camera-to-world [4, 4] at `eye` looking at `target`, image 'up' towards `up`."""
    eye = np.asarray(eye, np.float64)
    z = np.asarray(target, np.float64) - eye
    z /= np.linalg.norm(z)
    up = np.asarray(up, np.float64)
    if abs(np.dot(z, up / np.linalg.norm(up))) > 0.999:
        up = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, eye
    return c2w


def undistort_image(camera: Camera, image: np.ndarray, *, nearest: bool = False) -> tuple[np.ndarray, Camera]:
    """Resample `image` [H, W, ...] to the pinhole camera with the same K; returns (image, pinhole camera).

    `nearest` keeps label images (masks) binary.
    """
    if camera.is_pinhole:
        return image, camera
    h, w = image.shape[:2]
    if (w, h) != (camera.width, camera.height):
        raise ValueError(f"image is {w}x{h} but its camera says {camera.width}x{camera.height}")
    # cv2's maps use integer pixel centres; our K uses +0.5 centres, so shift the principal point.
    k_cv = camera.K.copy()
    k_cv[:2, 2] -= 0.5
    map1, map2 = cv2.initUndistortRectifyMap(k_cv, camera.dist, None, k_cv, (w, h), cv2.CV_32FC1)
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return cv2.remap(image, map1, map2, interp, borderMode=cv2.BORDER_REPLICATE), camera.pinhole()

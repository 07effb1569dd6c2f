"""Exact synthetic views of planar textures (calibration boards, fiducials, rig walls) for tests and benchmarks.

Each textured plane maps to the image by a homography; every (supersampled) pixel is sent back
through the inverse homography, which also gives its depth (1 / w), so planes partly behind the
camera and planes hiding each other render correctly. Supersampling then INTER_AREA averaging
integrates each pixel's footprint, so corners land where the projection says, to a few
hundredths of a pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration.board import BoardSpec, board_image
from calibration.camera import Camera, look_at_c2w


@dataclass(frozen=True)
class TexturedPlane:
    """`texture` float32 [h, w] or [h, w, 3]; texture pixel (i, j) covers plane [i*m, (i+1)*m) x [j*m, (j+1)*m), m = `metres_per_px`.

    `plane_to_world` [4, 4]: the plane's x, y axes and its origin (the texture's top-left corner).
    """

    texture: np.ndarray
    plane_to_world: np.ndarray
    metres_per_px: float


def translation(t) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


def board_plane(spec: BoardSpec, board_to_world: np.ndarray, px_per_square: int = 40) -> TexturedPlane:
    """The printed board as a plane; `board_to_world` places the board frame of `spec.object_points()`."""
    img = board_image(spec, px_per_square).astype(np.float32) / 255.0
    margin_px = (img.shape[1] - spec.squares[0] * px_per_square) // 2
    m = spec.square_m / px_per_square
    # Object-point origin: the board's outer corner (ChArUco) or its first inner corner (chessboard).
    origin_px = margin_px + (px_per_square if spec.kind == "chessboard" else 0)
    return TexturedPlane(img, board_to_world @ translation([-origin_px * m, -origin_px * m, 0.0]), m)


def marker_plane(dictionary: str, marker_id: int, side_m: float, marker_to_world: np.ndarray, px: int = 60) -> TexturedPlane:
    """An ArUco marker with a white border of one module; `marker_to_world` places the marker's top-left corner."""
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    img = cv2.aruco.generateImageMarker(d, marker_id, px, borderBits=1)
    bits = d.markerSize + 2
    pad = px // bits
    img = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255).astype(np.float32) / 255.0
    m = side_m / px
    return TexturedPlane(img, marker_to_world @ translation([-pad * m, -pad * m, 0.0]), m)


def noise_texture(size: tuple[int, int], rng: np.random.Generator, octaves: int = 5) -> np.ndarray:
    """Gray texture [h, w] in [0, 1]: blotches at several scales plus sharp shapes (features for ORB/SIFT)."""
    h, w = size
    out = np.zeros((h, w), np.float32)
    for o in range(octaves):
        cells = 4 * 2**o
        small = rng.random((max(2, h * cells // max(h, w)), cells)).astype(np.float32)
        out += cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC) / 2 ** (0.6 * o)
    out -= out.min()
    out /= out.max()
    # Sharp-edged clutter (panels, bolts, labels): corners that feature detectors lock on to.
    for _ in range(h * w // 900):
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        r = int(rng.integers(2, max(3, min(h, w) // 24)))
        tone = float(rng.random())
        if rng.random() < 0.5:
            cv2.rectangle(out, (c[0] - r, c[1] - r // 2), (c[0] + r, c[1] + r // 2), tone, -1)
        else:
            cv2.circle(out, c, r, tone, -1)
    return out


def render_planes(camera: Camera, planes: list[TexturedPlane], background: float = 0.5, supersample: int = 3) -> np.ndarray:
    """Gray float32 image [H, W] of `planes` seen by pinhole `camera` (its c2w in world coordinates)."""
    s = supersample
    h, w = camera.height * s, camera.width * s
    out = np.full((h, w), background, np.float32)
    zbuf = np.full((h, w), np.inf, np.float32)
    viewmat = camera.viewmat
    for plane in planes:
        p2c = viewmat @ plane.plane_to_world
        th, tw = plane.texture.shape[:2]
        x0, y0, x1, y1 = _window(camera, p2c, tw * plane.metres_per_px, th * plane.metres_per_px, s)
        if x1 <= x0 or y1 <= y0:
            continue
        # Continuous coordinates of the supersampled pixel centres in the window, in camera pixel units.
        uu, vv = np.meshgrid((np.arange(x0, x1) + 0.5) / s, (np.arange(y0, y1) + 0.5) / s)
        inv = np.linalg.inv(camera.K @ p2c[:3][:, [0, 1, 3]])
        q0 = inv[0, 0] * uu + inv[0, 1] * vv + inv[0, 2]
        q1 = inv[1, 0] * uu + inv[1, 1] * vv + inv[1, 2]
        q2 = inv[2, 0] * uu + inv[2, 1] * vv + inv[2, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = 1.0 / q2
            a = (q0 * depth / plane.metres_per_px - 0.5).astype(np.float32)
            b = (q1 * depth / plane.metres_per_px - 0.5).astype(np.float32)
        zwin = zbuf[y0:y1, x0:x1]
        hit = (depth > 0) & (a >= -0.5) & (a <= tw - 0.5) & (b >= -0.5) & (b <= th - 0.5) & (depth < zwin)
        if not hit.any():
            continue
        tex = plane.texture if plane.texture.ndim == 2 else plane.texture.mean(-1)
        sample = cv2.remap(tex, a, b, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out[y0:y1, x0:x1][hit] = sample[hit]
        zwin[hit] = depth[hit]
    return cv2.resize(out, (camera.width, camera.height), interpolation=cv2.INTER_AREA) if s > 1 else out


def _window(camera: Camera, p2c: np.ndarray, width_m: float, height_m: float, s: int) -> tuple[int, int, int, int]:
    """Supersampled pixel window (x0, y0, x1, y1) holding the plane's image; the whole image if it crosses the camera plane."""
    w, h = camera.width * s, camera.height * s
    corners = np.array([[0, 0, 0, 1], [width_m, 0, 0, 1], [0, height_m, 0, 1], [width_m, height_m, 0, 1.0]]) @ p2c.T
    if np.any(corners[:, 2] <= 1e-9):
        return 0, 0, w, h
    uv = corners[:, :2] / corners[:, 2:3] @ camera.K[:2, :2].T + camera.K[:2, 2]
    lo = np.floor(uv.min(0) * s).astype(int) - 2
    hi = np.ceil(uv.max(0) * s).astype(int) + 2
    return max(lo[0], 0), max(lo[1], 0), min(hi[0], w), min(hi[1], h)


def sensor(
    image: np.ndarray, rng: np.random.Generator, *, noise: float = 0.01, blur_sigma: float = 0.0, gain: float = 1.0, offset: float = 0.0
) -> np.ndarray:
    """Optics and sensor: Gaussian blur, exposure gain/offset, read noise; uint8 [H, W]."""
    img = image.astype(np.float32)
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    img = img * gain + offset + rng.normal(0.0, noise, img.shape).astype(np.float32)
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def ring_rig(
    num_cameras: int,
    *,
    radius: float = 0.8,
    arc_deg: float = 100.0,
    width: int = 640,
    height: int = 480,
    focal: float = 700.0,
    height_m: float = 0.25,
) -> list[Camera]:
    """Cameras on an arc around the origin (z up), all looking at it; rig frame = world frame."""
    k = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
    cams = []
    for az in np.radians(np.linspace(-arc_deg / 2, arc_deg / 2, num_cameras)):
        eye = np.array([radius * np.sin(az), -radius * np.cos(az), height_m])
        cams.append(Camera(k, width, height, np.zeros(0), look_at_c2w(eye, np.zeros(3))))
    return cams


def random_board_poses(
    spec: BoardSpec, count: int, rng: np.random.Generator, *, max_tilt_deg: float = 35.0, spread_m: float = 0.12
) -> list[np.ndarray]:
    """Board-to-world poses near the origin facing the ring rig (board normal towards -y), tilted at random."""
    from calibration.so3 import axis_angle_to_matrix

    w, h = spec.size_m
    poses = []
    for _ in range(count):
        # Board x along world x, board y down (world -z), board z (into the board) along world +y.
        base = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
        tilt = axis_angle_to_matrix(np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg, 3)) * [1, 1, 0.3])
        r = tilt @ base
        centre = rng.uniform(-spread_m, spread_m, 3) * [1, 0.5, 1]
        t = centre - r @ np.array([w / 2, h / 2, 0.0])
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = r, t
        poses.append(m)
    return poses


def close_up_board_poses(
    camera: Camera, spec: BoardSpec, count: int, rng: np.random.Generator, *, fill: float = 0.7, max_tilt_deg: float = 40.0
) -> list[np.ndarray]:
    """Board-to-world poses close to one camera, the board filling ~`fill` of the image width, tilted at random.

    These are the views that pin a camera's intrinsics (principal point and distortion need the
    board near the image edges and seen in perspective); only this camera sees them.
    """
    from calibration.so3 import axis_angle_to_matrix

    w, h = spec.size_m
    dist = camera.K[0, 0] * w / (fill * camera.width)
    poses = []
    for _ in range(count):
        tilt = axis_angle_to_matrix(np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg, 3)) * [1, 1, 0.2])
        # Board axes aligned with the camera's, then tilted; its centre wanders over the image.
        r = camera.c2w[:3, :3] @ tilt
        shift = rng.uniform(-0.25, 0.25, 2) * [camera.width, camera.height] / camera.K[0, 0] * dist
        centre_cam = np.array([shift[0], shift[1], dist])
        centre = camera.c2w[:3, :3] @ centre_cam + camera.c2w[:3, 3]
        m = np.eye(4)
        m[:3, :3] = r
        m[:3, 3] = centre - r @ np.array([w / 2, h / 2, 0.0])
        poses.append(m)
    return poses


def rig_board_views(
    spec: BoardSpec,
    cameras: dict[str, Camera],
    rng: np.random.Generator,
    *,
    shared: int = 12,
    close_ups: int = 8,
    noise: float = 0.01,
    blur_sigma: float = 0.5,
    supersample: int = 2,
) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, np.ndarray]]:
    """Board images as a rig calibration session takes them: `shared` frames near the rig's centre
    (every camera shoots; some may not see the board) and `close_ups` per camera (only it shoots).

    Returns (images[camera][frame] uint8 [H, W], board_to_world[frame]).
    """
    frames = {f"shared{j:02d}": (p, None) for j, p in enumerate(random_board_poses(spec, shared, rng))}
    for name, cam in cameras.items():
        for k, p in enumerate(close_up_board_poses(cam, spec, close_ups, rng)):
            frames[f"{name}_close{k:02d}"] = (p, name)
    images: dict[str, dict[str, np.ndarray]] = {n: {} for n in cameras}
    for frame, (pose, only) in frames.items():
        plane = board_plane(spec, pose)
        for name, cam in cameras.items():
            if only is None or only == name:
                images[name][frame] = sensor(render_planes(cam, [plane], supersample=supersample), rng, noise=noise, blur_sigma=blur_sigma)
    return images, {f: p for f, (p, _) in frames.items()}


def _frame(x_axis, y_axis, origin) -> np.ndarray:
    x = np.asarray(x_axis, float)
    y = np.asarray(y_axis, float)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, np.cross(x, y), origin
    return m


def rig_frame_scene(
    rng: np.random.Generator,
    *,
    half_x: float = 1.0,
    half_y: float = 1.0,
    z_lo: float = -0.5,
    z_hi: float = 1.0,
    fiducials: bool = True,
    marker_m: float = 0.1,
) -> tuple[list[TexturedPlane], dict | None]:
    """The static surroundings of a ring rig: the inside of a box with textured walls, and
    optionally ArUco fiducials (DICT_4X4_50) on the far wall and the floor.

    Returns (planes, fiducials) with fiducials = {"dictionary", "marker_m", "markers": {id: [4, 3]
    corners in the rig frame, ArUco order TL TR BR BL}} or None.
    """
    tex_px = 512
    walls = [
        _frame([1, 0, 0], [0, 0, -1], [-half_x, half_y, z_hi]),  # far wall (y = +half_y)
        _frame([1, 0, 0], [0, 1, 0], [-half_x, -half_y, z_lo]),  # floor
        _frame([0, 1, 0], [0, 0, -1], [-half_x, -half_y, z_hi]),  # left wall
        _frame([0, -1, 0], [0, 0, -1], [half_x, half_y, z_hi]),  # right wall
        _frame([-1, 0, 0], [0, 0, -1], [half_x, -half_y, z_hi]),  # near wall
        _frame([1, 0, 0], [0, -1, 0], [-half_x, half_y, z_hi]),  # ceiling
    ]
    planes = []
    for w in walls:
        size = max(2 * half_x, 2 * half_y, z_hi - z_lo)
        planes.append(TexturedPlane(0.15 + 0.7 * noise_texture((tex_px, tex_px), rng), w, size / tex_px))
    if not fiducials:
        return planes, None
    markers = {}
    eps = 1e-3
    spots = [(x, z) for x in (-0.6, -0.2, 0.2, 0.6) for z in (-0.1, -0.32)]
    for i, (x, z) in enumerate(spots):
        m = _frame([1, 0, 0], [0, 0, -1], [x - marker_m / 2, half_y - eps, z + marker_m / 2])
        planes.append(marker_plane("DICT_4X4_50", i, marker_m, m))
        markers[i] = _marker_corners(m, marker_m)
    for j, (x, y) in enumerate([(-0.5, 0.55), (0.0, 0.65), (0.5, 0.55)]):
        # Seen from above: the marker frame's z (into the marker) must point down, or it prints mirrored.
        m = _frame([1, 0, 0], [0, -1, 0], [x - marker_m / 2, y + marker_m / 2, z_lo + eps])
        planes.append(marker_plane("DICT_4X4_50", len(spots) + j, marker_m, m))
        markers[len(spots) + j] = _marker_corners(m, marker_m)
    return planes, {"dictionary": "DICT_4X4_50", "marker_m": marker_m, "markers": {k: v.tolist() for k, v in markers.items()}}


def _marker_corners(marker_to_world: np.ndarray, side: float) -> np.ndarray:
    local = np.array([[0, 0, 0, 1], [side, 0, 0, 1], [side, side, 0, 1], [0, side, 0, 1.0]])
    return (local @ marker_to_world.T)[:, :3]

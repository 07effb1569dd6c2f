import cv2
import numpy as np
import pytest

from calibration.camera import (
    Camera,
    c2w_opencv_to_opengl,
    c2w_opengl_to_opencv,
    invert_rigid,
    look_at_c2w,
    project_points,
    undistort_image,
)
from calibration.so3 import axis_angle_to_matrix


def random_camera(rng: np.random.Generator, n_dist: int) -> Camera:
    w, h = int(rng.integers(200, 1200)), int(rng.integers(200, 1200))
    f = rng.uniform(0.6, 1.5) * w
    k = np.array([[f, 0, w / 2 + rng.uniform(-20, 20)], [0, f * rng.uniform(0.95, 1.05), h / 2 + rng.uniform(-20, 20)], [0, 0, 1]])
    dist = np.zeros(n_dist)
    if n_dist:
        dist[:4] = rng.normal(0, [0.1, 0.05, 1e-3, 1e-3])
    if n_dist >= 5:
        dist[4] = rng.normal(0, 0.01)
    if n_dist >= 8:
        dist[5:8] = rng.normal(0, [0.05, 0.01, 0.005])
    if n_dist >= 12:
        dist[8:12] = rng.normal(0, 1e-3, 4)
    c2w = np.eye(4)
    c2w[:3, :3] = axis_angle_to_matrix(rng.normal(0, 1, 3))
    c2w[:3, 3] = rng.normal(0, 2, 3)
    return Camera(k, w, h, dist, c2w)


@pytest.mark.parametrize("n_dist", [0, 4, 5, 8, 12])
def test_project_matches_cv2_project_points(n_dist):
    rng = np.random.default_rng(n_dist)
    for _ in range(20):
        cam = random_camera(rng, n_dist)
        # Points in front of the camera, spread to the image corners where distortion is largest.
        local = np.column_stack([rng.uniform(-0.5, 0.5, (200, 2)), np.ones(200)]) * rng.uniform(0.5, 10, (200, 1))
        world = local @ cam.c2w[:3, :3].T + cam.c2w[:3, 3]
        uv, depth = cam.project(world)
        vm = cam.viewmat
        rvec, _ = cv2.Rodrigues(vm[:3, :3])
        ref, _ = cv2.projectPoints(world, rvec, vm[:3, 3], cam.K, cam.dist if n_dist else None)
        assert np.abs(uv - ref[:, 0]).max() <= 1e-6
        np.testing.assert_allclose(depth, local[:, 2], rtol=1e-12)


@pytest.mark.parametrize("n_dist", [0, 4, 5, 8, 12])
def test_unproject_inverts_project(n_dist):
    rng = np.random.default_rng(10 + n_dist)
    cam = random_camera(rng, n_dist)
    local = np.column_stack([rng.uniform(-0.4, 0.4, (500, 2)), np.ones(500)]) * rng.uniform(0.5, 10, (500, 1))
    world = local @ cam.c2w[:3, :3].T + cam.c2w[:3, 3]
    uv, depth = cam.project(world)
    back = cam.unproject(uv, depth)
    assert np.abs(back - world).max() < 1e-12


def test_points_behind_camera_are_flagged():
    cam = Camera(np.array([[100.0, 0, 50], [0, 100, 50], [0, 0, 1]]), 100, 100)
    uv, depth = cam.project(np.array([[0, 0, -1.0], [0, 0, 0.0], [0, 0, 2.0]]))
    assert depth[0] < 0 and np.isnan(uv[0]).all() and np.isnan(uv[1]).all()
    np.testing.assert_allclose(uv[2], [50, 50])


def test_project_points_in_the_camera_frame_with_a_near_plane():
    k = np.array([[100.0, 0, 50], [0, 100, 50], [0, 0, 1]])
    uv, z = project_points(np.array([[0.1, -0.2, 1.0], [0.0, 0.0, 1e-7]]), k, near=1e-6)
    np.testing.assert_allclose(uv[0], [60, 30])
    assert z[1] == 1e-7 and np.isnan(uv[1]).all()


def test_pixel_centre_convention():
    # A ray through the optical axis lands at cx; pixel (0, 0)'s centre is (0.5, 0.5).
    cam = Camera(np.array([[10.0, 0, 2.0], [0, 10, 2.0], [0, 0, 1]]), 4, 4)
    ray = cam.pixel_rays_camera(np.array([[0.5, 0.5]]))
    np.testing.assert_allclose(ray, [[-0.15, -0.15, 1.0]])


def test_opengl_conversion_roundtrip_and_axes():
    c2w = look_at_c2w(np.array([2.0, 0, 0]), np.zeros(3))
    gl = c2w_opencv_to_opengl(c2w)
    # OpenGL cameras look down their -z axis: towards the target.
    np.testing.assert_allclose(-gl[:3, 2], [-1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(c2w_opengl_to_opencv(gl), c2w)


def test_viewmat_is_inverse_of_c2w():
    rng = np.random.default_rng(3)
    cam = random_camera(rng, 0)
    np.testing.assert_allclose(cam.viewmat @ cam.c2w, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(invert_rigid(cam.viewmat), cam.c2w, atol=1e-12)


def test_look_at_points_camera_at_target():
    c2w = look_at_c2w(np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 0.5]))
    cam = Camera(np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]]), 320, 240, c2w=c2w)
    uv, depth = cam.project(np.array([[0.0, 0.0, 0.5]]))
    np.testing.assert_allclose(uv, [[160, 120]], atol=1e-9)
    # Image "up" is world +z: a point above the target projects above the centre (smaller v).
    uv_up, _ = cam.project(np.array([[0.0, 0.0, 0.6]]))
    assert uv_up[0, 1] < 120


def test_scaled_camera_keeps_projections_proportional():
    rng = np.random.default_rng(5)
    cam = random_camera(rng, 0)
    half = cam.scaled(cam.width // 2, cam.height // 2)
    pts = cam.unproject(np.array([[10.0, 20.0], [cam.width - 3.0, cam.height - 7.0]]), np.array([2.0, 3.0]))
    uv_full, _ = cam.project(pts)
    uv_half, _ = half.project(pts)
    np.testing.assert_allclose(uv_half, uv_full * [half.width / cam.width, half.height / cam.height], atol=1e-9)


def test_undistort_image_moves_pixels_to_pinhole_positions():
    k = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
    cam = Camera(k, 320, 240, np.array([-0.3, 0.1, 0.0, 0.0]))
    # A white dot at the distorted position of a 3D point must land at its pinhole position.
    pt = np.array([[0.3, 0.2, 1.0]])
    uv_d, _ = cam.project(pt)
    uv_p, _ = cam.pinhole().project(pt)
    img = np.zeros((240, 320), np.float32)
    iu, iv = np.floor(uv_d[0]).astype(int)
    img[iv - 1 : iv + 2, iu - 1 : iu + 2] = 1.0
    und, pin = undistort_image(cam, img)
    assert pin.is_pinhole
    ys, xs = np.nonzero(und > 0.5)
    centre = np.array([xs.mean() + 0.5, ys.mean() + 0.5])
    assert np.linalg.norm(centre - uv_p[0]) < 1.0


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"K": np.full((3, 3), np.nan)}, "finite"),
        ({"dist": np.zeros(3)}, "distortion"),
        ({"c2w": np.diag([1.0, 1.0, -1.0, 1.0])}, "rigid"),
        ({"width": 0}, "size"),
    ],
)
def test_invalid_cameras_raise_one_clear_sentence(kwargs, message):
    args = {"K": np.array([[100.0, 0, 50], [0, 100, 50], [0, 0, 1]]), "width": 100, "height": 100}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        Camera(**args)

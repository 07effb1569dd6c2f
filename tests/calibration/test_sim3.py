import numpy as np
import pytest

from calibration.sim3 import DegenerateError, Sim3, umeyama
from calibration.so3 import (
    axis_angle_to_matrix,
    geodesic_angle_deg,
    is_rotation,
    matrix_to_quat,
    quat_to_matrix,
    rotation_between,
)


def random_sim3(rng, scale=None) -> Sim3:
    return Sim3(
        scale if scale is not None else float(np.exp(rng.normal())), axis_angle_to_matrix(rng.normal(0, 1.5, 3)), rng.normal(0, 3, 3)
    )


def test_compose_inverse_and_apply():
    rng = np.random.default_rng(0)
    a, b = random_sim3(rng), random_sim3(rng)
    x = rng.normal(size=(50, 3))
    np.testing.assert_allclose((a @ b).apply(x), a.apply(b.apply(x)), atol=1e-12)
    np.testing.assert_allclose(a.inverse().apply(a.apply(x)), x, atol=1e-12)
    np.testing.assert_allclose((a @ a.inverse()).matrix(), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(Sim3.from_matrix(a.matrix()).matrix(), a.matrix(), atol=1e-12)


def test_apply_to_c2w_moves_centre_and_keeps_rigid_axes():
    rng = np.random.default_rng(1)
    s = random_sim3(rng, scale=2.5)
    c2w = np.eye(4)
    c2w[:3, :3] = axis_angle_to_matrix(rng.normal(size=3))
    c2w[:3, 3] = rng.normal(size=3)
    out = s.apply_to_c2w(c2w)
    np.testing.assert_allclose(out[:3, 3], s.apply(c2w[:3, 3]), atol=1e-12)
    assert is_rotation(out[:3, :3], tol=1e-12)
    # A world point seen by the camera keeps its image direction after both are transformed.
    p = rng.normal(size=3)
    d_before = np.linalg.inv(c2w)[:3, :3] @ (p - c2w[:3, 3])
    d_after = np.linalg.inv(out)[:3, :3] @ (s.apply(p) - out[:3, 3])
    np.testing.assert_allclose(d_after / np.linalg.norm(d_after), d_before / np.linalg.norm(d_before), atol=1e-12)


def test_reflections_are_rejected():
    with pytest.raises(ValueError, match="reflection"):
        Sim3(1.0, np.diag([1.0, 1.0, -1.0]), np.zeros(3))
    with pytest.raises(ValueError, match="reflection"):
        Sim3.from_matrix(np.diag([2.0, 2.0, -2.0, 1.0]))
    with pytest.raises(ValueError, match="scale"):
        Sim3(-1.0, np.eye(3), np.zeros(3))


def test_det_stays_plus_one_under_repeated_composition():
    rng = np.random.default_rng(2)
    steps = [Sim3(1.0, axis_angle_to_matrix(rng.normal(0, 0.3, 3)), rng.normal(0, 0.01, 3)) for _ in range(50)]
    acc = Sim3.identity()
    for i in range(20000):
        acc = steps[i % 50] @ acc
    r = acc.rotation
    assert abs(np.linalg.det(r) - 1.0) < 1e-12
    assert np.abs(r @ r.T - np.eye(3)).max() < 1e-12


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
@pytest.mark.parametrize("weighted", [False, True])
def test_umeyama_recovers_transform_across_scales(scale, weighted):
    rng = np.random.default_rng(int(scale * 1000) % 97)
    truth = Sim3(scale, axis_angle_to_matrix(rng.normal(size=3)), rng.normal(0, 1, 3) * scale)
    # Millimetre-sized and kilometre-sized point clouds alike.
    src = rng.normal(size=(40, 3)) * (1.0 / scale)
    dst = truth.apply(src)
    w = rng.uniform(0.1, 2.0, 40) if weighted else None
    fit = umeyama(src, dst, w)
    assert abs(fit.scale / scale - 1.0) < 1e-10
    assert geodesic_angle_deg(fit.rotation, truth.rotation) < 1e-8
    np.testing.assert_allclose(fit.apply(src), dst, rtol=0, atol=1e-9 * np.abs(dst).max())


def test_umeyama_weights_ignore_outliers():
    rng = np.random.default_rng(4)
    truth = random_sim3(rng)
    src = rng.normal(size=(30, 3))
    dst = truth.apply(src)
    dst[:5] += 10.0
    w = np.ones(30)
    w[:5] = 0.0
    fit = umeyama(src, dst, w)
    np.testing.assert_allclose(fit.matrix(), truth.matrix(), atol=1e-9)


def test_umeyama_never_returns_a_reflection():
    rng = np.random.default_rng(5)
    src = rng.normal(size=(20, 3))
    dst = src * np.array([1.0, 1.0, -1.0])  # a mirror image
    fit = umeyama(src, dst)
    assert np.linalg.det(fit.rotation) > 0


@pytest.mark.parametrize(
    "src, message",
    [
        (np.ones((10, 3)), "coincide"),
        (np.outer(np.linspace(0, 1, 10), [1.0, 2.0, 3.0]), "collinear"),
        (np.eye(3)[:2], "at least 3"),
    ],
)
def test_umeyama_degenerate_sets_raise_clear_errors(src, message):
    with pytest.raises(DegenerateError, match=message):
        umeyama(src, src + 1.0)


def test_quaternion_roundtrip_and_convention():
    rng = np.random.default_rng(6)
    r = axis_angle_to_matrix(rng.normal(size=(100, 3)))
    q = matrix_to_quat(r)
    assert np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(quat_to_matrix(q), r, atol=1e-12)
    # wxyz: 90 degrees about z.
    np.testing.assert_allclose(quat_to_matrix(np.array([np.sqrt(0.5), 0, 0, np.sqrt(0.5)])), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)


def test_geodesic_angle_is_precise_for_tiny_rotations():
    r = axis_angle_to_matrix(np.array([0.0, 0.0, np.radians(1e-6)]))
    assert abs(geodesic_angle_deg(np.eye(3), r) - 1e-6) < 1e-12


def test_rotation_between_handles_antiparallel():
    a = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0, 0]])
    b = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0, 0]])
    r = rotation_between(a, b)
    assert np.all(np.isfinite(r))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", r, a), b, atol=1e-12)

"""Rotations: quaternion <-> matrix conversions, the Hamilton product, rotation vectors and the
geodesic angle between rotations (precise near zero, where good registrations live)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.so3 import axis_angle_to_matrix, geodesic_angle_deg, matrix_to_quat, quat_multiply, quat_to_matrix


def _rot(axis: str, deg: float) -> np.ndarray:
    return Rotation.from_euler(axis, deg, degrees=True).as_matrix()


def test_geodesic_angle_by_hand() -> None:
    assert geodesic_angle_deg(np.eye(3), _rot("z", 30)) == pytest.approx(30.0)
    assert geodesic_angle_deg(_rot("x", 10), _rot("x", -25)) == pytest.approx(35.0)
    assert geodesic_angle_deg(np.eye(3), _rot("y", 180)) == pytest.approx(180.0)
    # Composition with a common rotation does not change the angle between two rotations.
    q = _rot("x", 40) @ _rot("y", -70)
    assert geodesic_angle_deg(q @ _rot("z", 5), q) == pytest.approx(5.0)
    batch = np.stack([_rot("z", d) for d in (0, 1, 2)])
    np.testing.assert_allclose(geodesic_angle_deg(batch, np.eye(3)), [0, 1, 2], atol=1e-12)


def test_geodesic_angle_keeps_its_precision_near_zero() -> None:
    # cos(1e-7 deg) rounds to 1.0, so arccos((trace - 1) / 2) would say 0; atan2 keeps the digits.
    tiny = 1e-7
    assert geodesic_angle_deg(np.eye(3), _rot("z", tiny)) == pytest.approx(tiny, rel=1e-6)


def test_quat_multiply_is_matrix_product_and_keeps_the_norm() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(5, 4)), rng.normal(size=(5, 4))
    assert quat_to_matrix(quat_multiply(a, b)) == pytest.approx(quat_to_matrix(a) @ quat_to_matrix(b), abs=1e-12)
    unit = a[:1] / np.linalg.norm(a[:1])
    assert np.linalg.norm(quat_multiply(unit, b), axis=-1) == pytest.approx(np.linalg.norm(b, axis=-1))


def test_quaternion_and_rotation_vector_round_trips() -> None:
    rng = np.random.default_rng(1)
    r = axis_angle_to_matrix(rng.normal(size=(4, 6, 3)))
    q = matrix_to_quat(r)
    assert q.shape == (4, 6, 4) and np.all(q[..., 0] >= 0)
    assert quat_to_matrix(q) == pytest.approx(r, abs=1e-12)
    assert axis_angle_to_matrix(np.array([0.0, 0.0, math.pi / 2])) == pytest.approx(_rot("z", 90), abs=1e-15)

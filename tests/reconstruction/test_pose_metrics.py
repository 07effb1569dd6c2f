"""Registration errors: geodesic rotation angle, camera-centre error, medians, symmetry sets."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from reconstruction.pose_metrics import camera_centers, center_error_pct, registration_errors


def _rot(axis: str, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _viewmat(R: np.ndarray, center: np.ndarray) -> np.ndarray:
    """World-to-camera 4x4 of a camera with rotation `R` sitting at `center`: t = -R c."""
    v = np.eye(4)
    v[:3, :3], v[:3, 3] = R, -R @ center
    return v


def test_camera_centres_and_centre_error() -> None:
    R = _rot("x", 20) @ _rot("z", 60)
    c = np.array([0.3, -1.2, 2.0])
    np.testing.assert_allclose(camera_centers(_viewmat(R, c)[None]), [c], atol=1e-12)
    # 0.1 m off, 2 m from the object -> 5 %; measured to a given object centre instead: 10 %.
    gt = np.array([[0.0, 0.0, 2.0]])
    assert center_error_pct(gt + [0.1, 0.0, 0.0], gt) == pytest.approx([5.0])
    assert center_error_pct(gt + [0.1, 0.0, 0.0], gt, object_center=[0.0, 0.0, 1.0]) == pytest.approx([10.0])


def _rig(n: int = 5) -> np.ndarray:
    """n ground-truth cameras about 2 m from the origin, each with a different orientation."""
    return np.stack([_viewmat(_rot("y", 360 * k / n) @ _rot("x", 15), np.array([np.sin(k), 0.5, 2.0])) for k in range(n)])


def test_registration_errors_are_medians_over_cameras() -> None:
    gt = _rig(3)
    centers = camera_centers(gt)
    moved = centers + [[0.0, 0.1, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]  # camera 0 is 0.1 m off
    est = np.stack([_viewmat(_rot("z", d) @ gt[k, :3, :3], moved[k]) for k, d in enumerate((1.0, 2.0, 10.0))])
    r = registration_errors(torch.from_numpy(est), gt)
    np.testing.assert_allclose(r["rotation_deg"], [1.0, 2.0, 10.0], atol=1e-9)
    assert r["rotation_deg_median"] == pytest.approx(2.0)
    np.testing.assert_allclose(r["center_pct"], [10.0 / np.linalg.norm(centers[0]), 0.0, 0.0], atol=1e-9)
    assert r["center_pct_median"] == pytest.approx(0.0, abs=1e-9) and r["symmetry"] is None


def _flipped(gt: np.ndarray, S: np.ndarray) -> np.ndarray:
    """The same cameras seeing the object turned by S: R -> R S^T, centre c -> S c."""
    est = gt.copy()
    for k in range(len(gt)):
        R = gt[k, :3, :3] @ S.T
        est[k] = _viewmat(R, S @ camera_centers(gt)[k])
    return est


def test_symmetric_object_is_not_charged_for_its_symmetry() -> None:
    gt = _rig()
    half_turn = _rot("z", 180)
    est = _flipped(gt, half_turn)
    plain = registration_errors(est, gt)
    np.testing.assert_allclose(plain["rotation_deg"], 180.0, atol=1e-9)
    assert plain["center_pct_median"] > 10.0
    sym = registration_errors(est, gt, symmetries=[_rot("x", 180), half_turn])
    assert sym["symmetry"] == 1
    np.testing.assert_allclose(sym["rotation_deg"], 0.0, atol=1e-6)
    np.testing.assert_allclose(sym["center_pct"], 0.0, atol=1e-9)


def test_one_symmetry_is_chosen_for_the_whole_capture() -> None:
    # Two of five cameras flipped is a broken registration, not a symmetric object: it must show.
    gt = _rig()
    half_turn = _rot("z", 180)
    est = gt.copy()
    est[:2] = _flipped(gt[:2], half_turn)
    r = registration_errors(est, gt, symmetries=[half_turn])
    assert r["symmetry"] is None
    np.testing.assert_allclose(r["rotation_deg"], [180, 180, 0, 0, 0], atol=1e-6)
    assert r["rotation_deg_median"] == pytest.approx(0.0, abs=1e-6)
    with pytest.raises(ValueError, match="viewmat"):
        registration_errors(est[:, :3], gt[:, :3])

"""Pose correction: 6D rotations stay rotations, identity at init, the paper's eq. (pose), mode choice (`presets.choose_pose_mode`)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from calibration.camera import look_at_c2w
from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix, is_rotation
from reconstruction.pose_correction import (
    POSE_MODES,
    PoseCorrection,
    extrinsics_error_px,
    rotation_6d_to_matrix,
    viewmats_from_c2w,
)
from reconstruction.presets import ConfigInputs, SceneStats, choose_pose_mode

STATS = SceneStats(5, 320, 240, (5000,) * 5, 120.0)


def corrected_c2w_numpy(correction: PoseCorrection, c2w: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return correction(torch.as_tensor(np.asarray(c2w, np.float64))).numpy()


def mode_of(**provenance) -> str:
    return choose_pose_mode(ConfigInputs(STATS, **provenance))


def ring(n=5):
    return np.stack([look_at_c2w(np.array([np.cos(a), np.sin(a), 0.3]) * 0.6, np.zeros(3)) for a in np.linspace(0, 6, n)])


def test_6d_rotation_is_always_a_rotation():
    r6 = torch.randn(2000, 6, dtype=torch.float64) * torch.logspace(-3, 3, 2000, dtype=torch.float64)[:, None]
    r = rotation_6d_to_matrix(r6).numpy()
    assert all(is_rotation(m, tol=1e-9) for m in r)
    # The first two columns of a rotation map back to it exactly.
    rot = axis_angle_to_matrix(np.array([0.3, -1.2, 2.0]))
    r6 = torch.tensor(np.concatenate([rot[:, 0], rot[:, 1]]))
    np.testing.assert_allclose(rotation_6d_to_matrix(r6).numpy(), rot, atol=1e-12)


@pytest.mark.parametrize("mode", ["global", "per_camera"])
def test_starts_at_identity(mode):
    c2w = ring()
    corr = PoseCorrection(len(c2w), mode)
    np.testing.assert_allclose(corrected_c2w_numpy(corr, c2w), c2w, atol=1e-14)
    assert sum(p.numel() for p in corr.rig_parameters()) == 10
    assert sum(p.numel() for p in corr.camera_parameters()) == (0 if mode == "global" else 9 * len(c2w))
    np.testing.assert_allclose(corr.delta_sim3().matrix(), np.eye(4), atol=1e-14)


def test_global_correction_is_the_papers_sim3():
    c2w = ring()
    corr = PoseCorrection(len(c2w), "global")
    rd = axis_angle_to_matrix(np.array([0.1, 0.2, -0.05]))
    with torch.no_grad():
        corr.rig_r6[0] = torch.tensor(np.concatenate([rd[:, 0], rd[:, 1]]) * 3.0)  # any positive scaling
        corr.rig_t[0] = torch.tensor([0.01, -0.02, 0.03])
        corr.rig_log_scale[0] = np.log(1.1)
    out = corrected_c2w_numpy(corr, c2w)
    delta = Sim3(1.1, rd, np.array([0.01, -0.02, 0.03]))
    np.testing.assert_allclose(out, delta.apply_to_c2w(c2w), atol=1e-12)
    np.testing.assert_allclose(corr.delta_sim3().matrix(), delta.matrix(), atol=1e-12)
    # Composing with the initial registration gives the refined registration of the rig.
    init = Sim3(2.0, axis_angle_to_matrix(np.array([0, 0, 1.0])), np.array([1.0, 0, 0]))
    rig = init.inverse().apply_to_c2w(c2w)
    np.testing.assert_allclose((corr.delta_sim3() @ init).apply_to_c2w(rig), out, atol=1e-10)


def test_per_camera_rotates_about_own_centre_and_has_gradients():
    c2w = ring(3)
    corr = PoseCorrection(3, "per_camera")
    with torch.no_grad():
        corr.cam_r6[1] = torch.tensor([np.cos(0.1), np.sin(0.1), 0, -np.sin(0.1), np.cos(0.1), 0])
    out = corrected_c2w_numpy(corr, c2w)
    np.testing.assert_allclose(out[:, :3, 3], c2w[:, :3, 3], atol=1e-14)  # centres unchanged
    np.testing.assert_allclose(out[[0, 2]], c2w[[0, 2]], atol=1e-14)
    vm = viewmats_from_c2w(corr(torch.tensor(c2w)))
    np.testing.assert_allclose(vm.detach().numpy() @ out, np.tile(np.eye(4), (3, 1, 1)), atol=1e-12)
    vm.sum().backward()
    assert corr.cam_r6.grad is not None and torch.all(torch.isfinite(corr.cam_r6.grad))


def test_per_camera_residuals_sit_on_the_rigs_sim3():
    # The rig's Sim(3) is what a new camera gets; each training camera adds its own SE(3) residual.
    c2w = ring(4)
    corr = PoseCorrection(4, "per_camera", pivot=np.array([0.01, 0.0, 0.02]), unit=0.05)
    rd = axis_angle_to_matrix(np.array([0.02, -0.01, 0.03]))
    rc = axis_angle_to_matrix(np.array([0.0, 0.01, 0.0]))
    with torch.no_grad():
        corr.rig_r6[0] = torch.tensor(np.concatenate([rd[:, 0], rd[:, 1]]))
        corr.rig_t[0] = torch.tensor([0.1, 0.0, -0.2])
        corr.cam_r6[2] = torch.tensor(np.concatenate([rc[:, 0], rc[:, 1]]))
        corr.cam_t[2] = torch.tensor([0.0, 0.3, 0.0])
    out = corrected_c2w_numpy(corr, c2w)
    rig = corr.delta_sim3().apply_to_c2w(c2w)
    np.testing.assert_allclose(out[[0, 1, 3]], rig[[0, 1, 3]], atol=1e-12)
    residual = np.eye(4)
    residual[:3, :3], residual[:3, 3] = rc, 0.05 * np.array([0.0, 0.3, 0.0])
    np.testing.assert_allclose(out[2], rig[2] @ residual, atol=1e-12)


def test_mode_from_provenance():
    assert mode_of(calibration_id="cal-7") == "global"
    assert mode_of(pose_source="rough") == "per_camera"
    assert mode_of() == "per_camera"  # nothing says how good the poses are
    assert mode_of(pose_source="rough", pose_mode="global") == "global"
    with pytest.raises(ValueError, match="pose mode"):
        mode_of(pose_mode="bogus")


def test_calibration_uncertainty_in_pixels_decides_the_mode():
    # 0.3 deg and 2 mm at 0.41 m with f = 386 px: about 2.0 + 2.0 px, above the 1 px a global correction tolerates.
    px = extrinsics_error_px({"rotation_deg": 0.3, "translation_mm": 2.0}, np.array([386.0, 386.0]), np.array([0.41, 0.40]))
    assert px == pytest.approx(386.0 * (np.radians(0.3) + 0.002 / 0.40))
    assert mode_of(calibration_id="cal-7", calibration_error_px=px) == "per_camera"
    # A board calibration's cross-check (0.04 deg, 0.4 mm) is a fraction of a pixel: the paper's global Sim(3).
    good = extrinsics_error_px({"rotation_deg": 0.04, "translation_mm": 0.4}, np.array([386.0]), np.array([0.41]))
    assert good < 1.0 and mode_of(calibration_id="cal-7", calibration_error_px=good) == "global"
    assert mode_of(calibration_id="cal-7", calibration_error_px=px, pose_mode="global") == "global"


def test_pivot_and_unit_keep_the_correction_a_sim3():
    # Rotating and scaling about the object's centre, translating in object radii: still one Sim(3)
    # that maps the cameras, and the refined registration composes exactly as without a pivot.
    c2w = ring()
    pivot, unit = np.array([0.3, -0.1, 0.05]), 0.07
    corr = PoseCorrection(len(c2w), "global", pivot=pivot, unit=unit)
    np.testing.assert_allclose(corrected_c2w_numpy(corr, c2w), c2w, atol=1e-14)
    rd = axis_angle_to_matrix(np.array([0.05, -0.1, 0.2]))
    with torch.no_grad():
        corr.rig_r6[0] = torch.tensor(np.concatenate([rd[:, 0], rd[:, 1]]))
        corr.rig_t[0] = torch.tensor([0.5, 0.2, -0.1])
        corr.rig_log_scale[0] = np.log(0.9)
    out = corrected_c2w_numpy(corr, c2w)
    delta = corr.delta_sim3()
    np.testing.assert_allclose(out, delta.apply_to_c2w(c2w), atol=1e-12)
    # The pivot moves only by the translation: c = pivot maps to pivot + unit * t.
    np.testing.assert_allclose(delta.apply(pivot[None])[0], pivot + unit * np.array([0.5, 0.2, -0.1]), atol=1e-12)
    with pytest.raises(ValueError, match="unit"):
        PoseCorrection(2, "global", unit=0.0)


def test_cli_offers_every_pose_mode():
    from deploy.commands.reconstruct import POSE_MODE_NAMES

    assert POSE_MODE_NAMES == POSE_MODES


def test_capture_states_its_calibration_uncertainty_in_its_own_units():
    from calibration.camera import Camera
    from reconstruction.pipeline import calibration_error_px

    # A rig in millimetres: cameras 400 mm from the object, f = 400 px.
    cams = [
        Camera.from_fov(2 * np.arctan(320 / 400), 640, 480, look_at_c2w(400.0 * np.array([np.cos(a), np.sin(a), 0.0]), np.zeros(3)))
        for a in (0.0, 2.0)
    ]
    meta = {"units": "mm", "calibration_uncertainty": {"rotation_deg": 0.0, "translation_mm": 2.0}}
    assert calibration_error_px(meta, cams, np.zeros(3)) == pytest.approx(400.0 * 2.0 / 400.0)
    assert calibration_error_px({"units": "mm"}, cams, np.zeros(3)) is None

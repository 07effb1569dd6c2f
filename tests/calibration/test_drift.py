"""Drift estimates on their own: pixel effect of a pose change, rotation from rays, background matching."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.drift import CHEAP, THOROUGH, background_drift, reprojection_effect_px, rotation_from_rays
from calibration.simulated import render_planes, rig_frame_scene, ring_rig, sensor
from calibration.so3 import axis_angle_to_matrix, geodesic_angle_deg


def test_effect_of_a_small_pan_is_focal_times_angle():
    cam = ring_rig(1, focal=800.0)[0]
    c2w = cam.c2w.copy()
    c2w[:3, :3] = c2w[:3, :3] @ axis_angle_to_matrix(np.radians([0.0, 0.1, 0.0]))
    # A little more than f * angle: off-axis points move further.
    assert reprojection_effect_px(cam, c2w, None) == pytest.approx(800 * np.radians(0.1), rel=0.07)
    moved = cam.c2w.copy()
    moved[:3, 3] += cam.c2w[:3, 0] * 0.001  # 1 mm sideways, seen at 1 m: 0.8 px
    assert reprojection_effect_px(cam, moved, 1.0) == pytest.approx(0.8, rel=0.01)
    assert reprojection_effect_px(cam, moved, None) == pytest.approx(0.0, abs=1e-9)


def test_rotation_from_rays_is_exact():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(50, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    r = axis_angle_to_matrix(np.array([0.01, -0.02, 0.005]))
    assert geodesic_angle_deg(rotation_from_rays(a, a @ r.T), r) < 1e-9


@pytest.mark.parametrize("mode,tol", [(CHEAP, 0.05), (THOROUGH, 0.01)])
def test_background_rotation_with_lighting_change(mode, tol):
    rng = np.random.default_rng(3)
    planes, _ = rig_frame_scene(rng, fiducials=False)
    cam = ring_rig(3, radius=0.5, arc_deg=60)[1]
    ref = sensor(render_planes(cam, planes, supersample=2), rng)
    turned = cam.c2w.copy()
    turned[:3, :3] = turned[:3, :3] @ axis_angle_to_matrix(np.radians([0.08, -0.06, 0.03]))
    img = sensor(render_planes(cam.with_c2w(turned), planes, supersample=2), rng, gain=0.75, offset=0.04)
    est = background_drift(cam, ref, img, mode=mode)
    assert est is not None and est.translation_mm is None
    assert geodesic_angle_deg(est.c2r[:3, :3], turned[:3, :3]) < tol
    assert est.rotation_deg == pytest.approx(np.degrees(np.linalg.norm(np.radians([0.08, -0.06, 0.03]))), abs=tol)


def test_background_without_texture_gives_no_estimate():
    cam = ring_rig(1)[0]
    flat = np.full((cam.height, cam.width), 128, np.uint8)
    assert background_drift(cam, flat, flat) is None

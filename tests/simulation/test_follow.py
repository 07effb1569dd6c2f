"""Gaussians follow rigid bodies: moving the body and moving the camera the opposite way give the
same image (positions, orientations and view-dependent colour all follow)."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera import Camera, invert_rigid, look_at_c2w
from calibration.so3 import axis_angle_to_matrix
from reconstruction.twin import load_twin, splat_normals
from simulation.follow import camera_path, render_bodies, splats_from_mesh, splats_from_twin, transform_splats
from simulation.scene import CameraSpec
from tests.simulation.twins import hammer, make_twin


def pose(rotvec, t) -> np.ndarray:
    p = np.eye(4)
    p[:3, :3] = axis_angle_to_matrix(np.asarray(rotvec, np.float64))
    p[:3, 3] = t
    return p


def test_transform_moves_means_and_turns_disk_normals():
    parts, rgb = hammer()
    s = splats_from_mesh(parts.vertices, parts.faces, rgb, parts.face_part, 500)
    p = pose([0.3, -1.2, 0.7], [0.1, 0.2, 0.3])
    m, q = transform_splats(s["means"], s["quats"], p)
    assert m == pytest.approx(s["means"] @ p[:3, :3].T + p[:3, 3], abs=1e-6)
    assert splat_normals(q.astype(np.float32)) == pytest.approx(splat_normals(s["quats"]) @ p[:3, :3].T, abs=1e-5)


def test_moving_the_body_equals_moving_the_camera_back(tmp_path):
    twin = load_twin(make_twin(tmp_path, "hammer", *hammer(), n=2000))
    s = splats_from_twin(twin)
    s["sh"] = s["sh"].copy()
    s["sh"][:, 1:] = np.random.default_rng(1).normal(scale=0.3, size=s["sh"][:, 1:].shape)  # strong view dependence
    cam = Camera.from_fov(np.deg2rad(50), 96, 72, look_at_c2w(np.array([0.35, -0.3, 0.25]), np.zeros(3)))
    body = pose([0.4, 0.2, 1.1], [0.02, -0.01, 0.03])
    moved, alpha = render_bodies([s], [body], cam)
    # Same relative geometry: body at rest, camera carried by the inverse motion.
    still, _ = render_bodies([s], [np.eye(4)], cam.with_c2w(invert_rigid(body) @ cam.c2w))
    assert alpha.mean() > 0.05  # the hammer is in view
    assert np.abs(moved - still).max() < 2e-3
    unmoved, _ = render_bodies([s], [np.eye(4)], cam)
    assert np.abs(moved - unmoved).mean() > 0.02  # and the motion did change the picture


def test_turntable_orbits_and_fixed_stays():
    spec = CameraSpec(mode="turntable", eye=(1.0, 0.0, 0.5), target=(0.0, 0.0, 0.0), turns=0.25, width=32, height=24)
    cams = camera_path(spec, 5)
    assert cams[0].center == pytest.approx([1, 0, 0.5]) and cams[-1].center == pytest.approx([0, 1, 0.5], abs=1e-12)
    fixed = camera_path(CameraSpec(mode="fixed", eye=(1.0, 0.0, 0.5), target=(0.0, 0.0, 0.0)), 3)
    assert all(np.allclose(c.c2w, fixed[0].c2w) for c in fixed)

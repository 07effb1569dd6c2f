"""Board-free relative calibration with pycolmap on a synthetic rig's surroundings."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.sfm import SfMError, align_to_reference, sfm_calibrate
from calibration.sim3 import Sim3
from calibration.simulated import render_planes, rig_frame_scene, ring_rig, sensor
from calibration.so3 import axis_angle_to_matrix, geodesic_angle_deg


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(0)
    planes, _ = rig_frame_scene(rng, fiducials=False)
    cams = {f"cam{i}": c for i, c in enumerate(ring_rig(6, radius=0.5, arc_deg=100))}
    images = {n: sensor(render_planes(c, planes, supersample=2), rng) for n, c in cams.items()}
    return cams, images


def test_sfm_recovers_the_rig(scene):
    cams, images = scene
    res = sfm_calibrate(images, cams, reference={n: c.c2w for n, c in cams.items()})
    assert (res.registered, res.total) == (6, 6)
    assert res.reprojection_px < 0.6 and res.points > 200
    for n, cam in cams.items():
        assert geodesic_angle_deg(cam.c2w[:3, :3], res.cameras[n].c2w[:3, :3]) < 1.0  # board-free: ~0.1-0.5 deg here
        assert np.linalg.norm(cam.c2w[:3, 3] - res.cameras[n].c2w[:3, 3]) < 0.02
        np.testing.assert_allclose(res.cameras[n].K, cam.K)  # intrinsics held fixed


def test_sfm_fails_loudly_on_an_image_it_cannot_place(scene):
    cams, images = scene
    rng = np.random.default_rng(1)
    bad = {**images, "cam3": (rng.random(images["cam3"].shape) * 255).astype(np.uint8)}
    with pytest.raises(SfMError, match=r"registered 5/6 images; cam3 could not be placed"):
        sfm_calibrate(bad, cams)


def test_alignment_uses_orientations():
    cams = {f"c{i}": c for i, c in enumerate(ring_rig(5, radius=0.5, arc_deg=60))}
    sim = Sim3(0.3, axis_angle_to_matrix(np.array([0.2, -0.4, 0.1])), np.array([0.1, 2.0, -1.0]))
    moved = {n: sim.inverse().apply_to_c2w(c.c2w) for n, c in cams.items()}
    est = align_to_reference(moved, {n: c.c2w for n, c in cams.items()})
    assert est.scale == pytest.approx(0.3, rel=1e-9)
    assert est.rotation_deg_to(sim) < 1e-6

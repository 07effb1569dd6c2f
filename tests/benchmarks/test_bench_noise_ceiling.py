"""The noise-ceiling benchmark's two measurements: the best Sim(3) the recorded cameras allow, and the
held-out silhouette IoU of a mesh placed by a Sim(3)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from benchmarks.bench_noise_ceiling import best_sim3, heldout_iou
from benchmarks.bench_rig_scenes import surface_points
from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix
from tests.reconstruction.test_registration import ring, scene, true_sim3


@pytest.fixture(scope="module")
def box():
    return trimesh.creation.box([0.08, 0.05, 0.03])


def test_noise_common_to_all_cameras_is_taken_by_the_sim3_and_the_rest_is_left(box):
    truth = true_sim3(box, 1.0, seed=5)
    _, cams = scene(box, ring(5, 0.5), truth)
    rig_c2w = np.stack([c.c2w for c in cams])
    Ks = np.stack([c.K for c in cams])
    points = surface_points(np.asarray(box.vertices), np.asarray(box.faces), 500)
    true_c2w = truth.apply_to_c2w(rig_c2w)
    # The whole rig moved: one Sim(3) explains it exactly.
    common = Sim3(1.0, axis_angle_to_matrix(np.array([0.0, 0.02, 0.0])), np.array([0.005, 0.0, 0.0]))
    fitted, rms, rms_start = best_sim3(rig_c2w, common.apply_to_c2w(true_c2w), Ks, points, truth)
    assert rms_start > 1.0 and rms < 1e-6
    np.testing.assert_allclose((common @ truth).matrix(), fitted.matrix(), atol=1e-8)
    # One camera off on its own: no Sim(3) explains it, and the fit stays near the truth.
    moved = true_c2w.copy()
    moved[0, :3, 3] += [0.003, 0.0, 0.0]
    fitted, rms, rms_start = best_sim3(rig_c2w, moved, Ks, points, truth)
    assert 0.0 < rms < rms_start
    assert np.linalg.norm(fitted.translation - truth.translation) < 0.003


def test_heldout_iou_is_one_at_the_truth_and_falls_when_the_mesh_is_misplaced(box):
    truth = true_sim3(box, 1.0, seed=6)
    masks, cams = scene(box, ring(4, 0.5), truth)
    assert heldout_iou(box.vertices, box.faces, cams, masks, truth) > 0.98
    off = Sim3(1.0, np.eye(3), np.array([0.01, 0.0, 0.0])) @ truth
    assert heldout_iou(box.vertices, box.faces, cams, masks, off) < 0.9


def test_no_shape_reaches_the_scissors_heldout_iou_of_0975_under_its_unstated_calibration_noise():
    """Issue 60 asks held-out IoU >= 0.975 at nominal poses on every rig scene. Held-out cameras inherit the rig
    Sim(3), which the noisy training cameras fix only so far: the true mesh itself, placed by the best Sim(3) those
    cameras allow, stays below 0.975 on the thin scissors (noise_ceiling.md)."""
    from benchmarks.bench_noise_ceiling import scene_row
    from tests.conftest import require_shared

    row = scene_row(require_shared("rig_scenes", "scenes", "037_scissors"), "all", None, None)
    assert row["iou_true"] > 0.995
    assert row["iou_best"] < 0.975

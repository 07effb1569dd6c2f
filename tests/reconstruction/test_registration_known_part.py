"""The known part again (conveyor search about the previous pose), the object's pose per camera with
its uncertainty, a silhouette score that degrades gracefully for a thin part, and images that tell a
near-symmetric turn from the true pose."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix, geodesic_angle_deg
from reconstruction.library import build_library
from reconstruction.registration import (
    RegistrationError,
    Scorer,
    area_centroid,
    known_part_register,
    photo_disagreement,
    rig_up,
    triangulate_centroid,
)
from tests.reconstruction.test_registration import GRID, bracket, ring, scene, true_sim3


@pytest.fixture(scope="module")
def lib(tmp_path_factory):
    d = tmp_path_factory.mktemp("meshes")
    bracket().export(d / "bracket.stl")
    trimesh.creation.box([0.08, 0.08, 0.08]).export(d / "cube.stl")
    return build_library(d, tmp_path_factory.mktemp("lib"), grid=GRID, workers=1, progress=False, log=lambda s: None)


def on_conveyor(gt: Sim3, yaw_deg: float, shift: np.ndarray, centre_obj: np.ndarray) -> Sim3:
    """The same part turned by `yaw_deg` about rig z through its centre `centre_obj` [3] and moved by `shift` [3]."""
    centre = gt.inverse().apply(centre_obj)
    turn = axis_angle_to_matrix(np.radians(yaw_deg) * np.array([0.0, 0.0, 1.0]))
    return gt @ Sim3(1.0, turn.T, centre - turn.T @ (centre + shift))


def test_rig_up_and_centroid_triangulation():
    mesh = bracket()
    gt = true_sim3(mesh, 1.0, seed=3)
    masks, cams = scene(mesh, ring(8, 0.5), gt)
    np.testing.assert_allclose(rig_up(cams), [0, 0, 1], atol=0.1)
    c = triangulate_centroid(masks, cams)
    # The silhouettes' centroids meet near the part's area centroid (a few mm for a 12 cm part).
    assert np.linalg.norm(c - gt.inverse().apply(area_centroid(mesh.vertices, mesh.faces))) < 0.006


@pytest.mark.parametrize("yaw_deg", [35.0, 170.0, -100.0])
def test_known_part_finds_the_new_yaw_and_position(lib, yaw_deg):
    mesh = bracket()
    previous = true_sim3(mesh, 1.0, seed=3)
    now = on_conveyor(previous, yaw_deg, np.array([0.02, -0.015, 0.0]), mesh.bounds.mean(0))
    masks, cams = scene(mesh, ring(8, 0.5), now)
    res = known_part_register(masks, cams, lib, "bracket", previous, rig_metres_per_unit=1.0)
    assert res.model_id == "bracket" and res.alternatives == []
    assert geodesic_angle_deg(res.sim3_rig_to_object.rotation, now.rotation) < 2.0
    centre = mesh.bounds.mean(0)
    assert np.linalg.norm(res.sim3_rig_to_object.inverse().apply(centre) - now.inverse().apply(centre)) < 0.004
    assert res.per_view_iou.min() > 0.9
    assert {"yaw_search", "refine", "total"} <= set(res.timings_s)


def test_known_part_without_prior_searches_that_model_only(lib):
    mesh = bracket()
    gt = true_sim3(mesh, 1.0, seed=7)
    masks, cams = scene(mesh, ring(8, 0.5), gt)
    res = known_part_register(masks, cams, lib, "bracket", None, rig_metres_per_unit=1.0)
    assert res.model_id == "bracket" and all(m == "bracket" for m, _ in res.alternatives)
    with pytest.raises(RegistrationError, match="not in the library"):
        known_part_register(masks, cams, lib, "nope", gt)


def test_pose_per_camera_with_uncertainty(lib):
    mesh = bracket()
    gt = true_sim3(mesh, 1.0, seed=11)
    masks, cams = scene(mesh, ring(8, 0.5), gt)
    res = known_part_register(masks, cams, lib, "bracket", gt, rig_metres_per_unit=1.0)
    assert len(res.camera_poses) == len(cams)
    for pose, cam in zip(res.camera_poses, cams):
        t = np.array(pose["T_cam_obj"])
        true = np.linalg.inv(gt.apply_to_c2w(cam.c2w))
        assert geodesic_angle_deg(t[:3, :3], true[:3, :3]) < 2.0
        assert np.linalg.norm(t[:3, 3] - true[:3, 3]) < 0.005
        # Sub-degree, millimetre-level: what silhouettes at 240 px pin down, neither zero nor the cap.
        assert 0.01 < pose["rotation_sigma_deg"] < 5.0 and 1e-5 < pose["translation_sigma"] < 0.01


def test_thin_part_score_degrades_gracefully():
    # A thin ring: a pose a few pixels off has almost no IoU left, but the objective still falls smoothly.
    ring_mesh = trimesh.creation.annulus(0.045, 0.05, 0.004)
    gt = true_sim3(ring_mesh, 1.0, seed=19)
    masks, cams = scene(ring_mesh, ring(6, 0.5), gt)
    scorer = Scorer(masks, cams, 240)
    objs, ious = [], []
    for shift in (0.0, 0.004, 0.008, 0.016):
        moved = Sim3(1.0, np.eye(3), np.array([shift, 0.0, 0.0])) @ gt
        iou, obj = scorer.scores(ring_mesh.vertices, ring_mesh.faces, moved)
        ious.append(iou.mean())
        objs.append(obj.mean())
    assert ious[0] > 0.9 and ious[2] < 0.45
    assert all(a > b for a, b in zip(objs, objs[1:]))
    # Beyond where IoU has collapsed, the objective still tells a near pose from a far one.
    assert objs[2] - objs[3] > 0.03


def test_scores_do_not_depend_on_threads_and_a_cut_short_score_keeps_its_views(monkeypatch):
    # Views are scored on the kernel threads when nothing cuts the sum short: any split gives the same
    # scores; with a bar, views are scored in order on one thread and the ones never reached stay 0.
    mesh = bracket()
    gt = true_sim3(mesh, 1.0, seed=23)
    masks, cams = scene(mesh, ring(7, 0.5), gt)
    scorer = Scorer(masks, cams, 160)
    off = Sim3(1.0, axis_angle_to_matrix(np.array([0.0, 0.0, 0.3])), np.array([0.01, 0.0, 0.0])) @ gt
    monkeypatch.setattr("reconstruction.parallel.num_threads", lambda: 1)
    one = scorer.scores(mesh.vertices, mesh.faces, off)
    monkeypatch.setattr("reconstruction.parallel.num_threads", lambda: 3)
    three = scorer.scores(mesh.vertices, mesh.faces, off)
    np.testing.assert_array_equal(one[0], three[0])
    np.testing.assert_array_equal(one[1], three[1])
    cut_iou, cut_obj = scorer.scores(mesh.vertices, mesh.faces, off, stop_below=len(cams) - 0.5)
    done = np.flatnonzero(cut_obj)
    assert 0 < len(done) < len(cams) and np.array_equal(done, np.arange(len(done)))
    np.testing.assert_array_equal(cut_obj[done], one[1][done])
    assert not cut_iou[len(done) :].any()


def test_images_tell_a_near_symmetric_turn_from_the_true_pose():
    # A box tapered at one end: a half turn about z nearly keeps its silhouettes, but its striped
    # texture no longer lines up across views. (An exact symmetry keeps the colours consistent too:
    # images cannot break it, and `photo_disagreement` does not claim to.)
    box = trimesh.creation.box([0.08, 0.06, 0.04]).subdivide()  # a vertex ring at x = 0 for the taper's hinge
    v = box.vertices.copy()
    v[:, 1] *= np.where(v[:, 0] > 0, 1.0 - 6.0 * v[:, 0], 1.0)
    box = trimesh.Trimesh(v, box.faces, process=False)
    fine = box.subdivide()  # the same surface, more colour samples
    gt = true_sim3(box, 1.0, seed=29)
    _, cams = scene(box, ring(6, 0.4), gt, size=(160, 120))
    images = []
    for cam in cams:
        cam_obj = cam.with_c2w(gt.apply_to_c2w(cam.c2w))
        rows, cols = np.mgrid[0:120, 0:160]
        dirs = cam_obj.c2w[:3, :3] @ np.linalg.solve(cam_obj.K, np.stack([cols.ravel() + 0.5, rows.ravel() + 0.5, np.ones(cols.size)]))
        hits, rays, _ = box.ray.intersects_location(np.repeat(cam_obj.c2w[None, :3, 3], cols.size, 0), dirs.T, multiple_hits=False)
        img = np.full((120 * 160, 3), 0.5)
        img[rays] = np.stack([0.5 + 0.5 * np.sin(150 * hits[:, 0]), 0.5 + 0.5 * np.cos(150 * hits[:, 1]), np.full(len(hits), 0.2)], 1)
        images.append(img.reshape(120, 160, 3))
    turned = Sim3(1.0, np.diag([-1.0, -1.0, 1.0]), np.zeros(3)) @ gt
    right = photo_disagreement(np.stack(images), cams, fine.vertices, fine.faces, gt)
    wrong = photo_disagreement(np.stack(images), cams, fine.vertices, fine.faces, turned)
    assert right < 0.5 * wrong

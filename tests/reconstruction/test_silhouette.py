"""Silhouette rasterizer (checked against MuJoCo's renderer), normalisation, packing, popcount IoU."""

from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh

from calibration.camera import Camera, look_at_c2w, project_points
from reconstruction.silhouette import closed_winding, fill_triangles, fit_canvas, iou, normalize_silhouette, pack, render_silhouette, unpack
from reconstruction.silhouette_index import best_iou, count_window, fibonacci_directions, popcount_rows
from tests.conftest import require_shared


def test_square_covers_exactly_the_pixels_whose_centres_are_inside():
    # Unit-depth square from x,y in [-0.25, 0.25] with f = 40 and principal point (20, 20): pixels 10..29.
    v = np.array([[-0.25, -0.25, 1.0], [0.25, -0.25, 1.0], [0.25, 0.25, 1.0], [-0.25, 0.25, 1.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    K = np.array([[40.0, 0, 20], [0, 40, 20], [0, 0, 1]])
    sil = render_silhouette(v, f, K, np.eye(4), 40, 40)
    expect = np.zeros((40, 40), bool)
    expect[10:30, 10:30] = True
    assert np.array_equal(sil, expect)


def _fill(vertices, faces, cam, winding):
    uv, z = project_points(vertices, cam.K, cam.viewmat, near=1e-6)
    out = np.zeros((cam.height, cam.width), bool)
    fill_triangles(uv, np.ascontiguousarray(faces, np.int64), z > 1e-6, out, winding)
    return out


def test_a_closed_surface_is_filled_by_the_faces_turned_away_from_any_camera_outside_or_in():
    rng = np.random.default_rng(0)
    # A rough closed surface (a noisy icosphere, folds and all) and a closed surface that is not convex (a torus).
    blob = trimesh.creation.icosphere(3)
    blob.vertices *= 1.0 + 0.15 * rng.standard_normal((len(blob.vertices), 1))
    for mesh in (blob, trimesh.creation.torus(1.0, 0.35)):
        winding = closed_winding(mesh.vertices, mesh.faces)
        assert winding == 1 and closed_winding(mesh.vertices, mesh.faces[:, ::-1]) == -1
        # Around it, and at its centre: inside the blob, in the torus' hole.
        views = [(3.5 * d, np.zeros(3)) for d in fibonacci_directions(6)] + [(np.full(3, 0.01), rng.standard_normal(3))]
        for eye, target in views:
            cam = Camera.from_fov(np.radians(70), 96, 72, look_at_c2w(eye, target))
            every = _fill(mesh.vertices, mesh.faces, cam, 0)
            assert every.any()
            assert np.array_equal(_fill(mesh.vertices, mesh.faces, cam, winding), every)
            assert np.array_equal(_fill(mesh.vertices, mesh.faces[:, ::-1], cam, -winding), every)


def test_an_open_surface_has_no_winding_to_fill_from():
    box = trimesh.creation.box()
    assert closed_winding(box.vertices, box.faces) == 1
    assert closed_winding(box.vertices, box.faces[1:]) == 0  # one face gone: a hole
    assert closed_winding(box.vertices, np.vstack([box.faces[:6], box.faces[6:, ::-1]])) == 0  # wound both ways
    assert closed_winding(np.zeros((0, 3)), np.zeros((0, 3), np.int64)) == 0


def test_matches_mujoco_segmentation():
    os.environ.setdefault("MUJOCO_GL", "egl")
    path = require_shared("objects", "ycb", "050_medium_clamp", "textured.obj")
    from rig.render_mujoco import SyntheticScene

    scene = SyntheticScene.from_mesh(path, texture_size=64)
    mesh = scene.mesh
    center = mesh.bounds.mean(0)
    cams = [Camera.from_fov(np.radians(45), 160, 120, look_at_c2w(center + 4 * mesh.radius * d, center)) for d in fibonacci_directions(4)]
    _, masks = scene.render(cams)
    for cam, ref in zip(cams, masks):
        ours = render_silhouette(mesh.vertices, mesh.faces, cam.K, cam.viewmat, cam.width, cam.height)
        assert iou(ours, ref) >= 0.98


def test_normalisation_is_invariant_to_roll_position_and_size():
    mask = np.zeros((200, 240), bool)
    mask[60:100, 50:170] = True
    mask[100:140, 50:80] = True  # an L: no symmetry
    base = normalize_silhouette(mask, 32)
    import cv2

    for angle_deg, scale, shift in ((30.0, 1.0, (0, 0)), (-75.0, 0.6, (20, -15)), (150.0, 1.3, (-10, 10))):
        m = cv2.getRotationMatrix2D((120, 120), angle_deg, scale)
        m[:, 2] += shift
        moved = cv2.warpAffine(mask.astype(np.uint8), m + [[0, 0, 80], [0, 0, 80]], (400, 400), flags=cv2.INTER_NEAREST).astype(bool)
        assert not (moved[0].any() or moved[-1].any() or moved[:, 0].any() or moved[:, -1].any())
        nz = normalize_silhouette(moved, 32)
        # The canonical canvas matches up to the 180-degree flip the matcher tries anyway.
        flipped = normalize_silhouette(moved, 32, angle=nz.angle + np.pi).canvas
        assert max(iou(nz.canvas, base.canvas), iou(flipped, base.canvas)) > 0.9
        assert nz.extent == pytest.approx(base.extent * scale, rel=0.06)
        d = np.degrees(nz.angle - base.angle + np.radians(angle_deg))  # cv2 angles are counter-clockwise
        assert min(abs((d + 90) % 180 - 90), 180) < 2.0


def test_fit_canvas_keeps_aspect_and_centres():
    out = fit_canvas(np.ones((10, 40), bool), 32)
    rows = np.flatnonzero(out.any(1))
    assert out[:, 0].any() and out[:, -1].any() and len(rows) == 8 and rows[0] == 12


def test_pack_roundtrip_and_popcount_iou():
    rng = np.random.default_rng(0)
    canvases = rng.random((50, 32, 32)) > 0.5
    words = pack(canvases)
    assert words.shape == (50, 16) and words.dtype == np.uint64
    assert np.array_equal(unpack(words, 32), canvases)
    counts = popcount_rows(words)
    assert np.array_equal(counts, canvases.reshape(50, -1).sum(1))
    best, which = best_iou(words, counts, words[[3, 7]])
    ref = np.array([[iou(c, canvases[q]) for q in (3, 7)] for c in canvases])
    assert np.allclose(best, ref.max(1), atol=1e-6)
    assert np.array_equal(which, ref.argmax(1))


def test_count_window_is_an_exact_prune():
    counts = np.arange(0, 1000, dtype=np.int32)
    lo, hi = count_window(counts, np.array([100]), 0.5)
    assert counts[lo] == 50 and counts[hi - 1] == 200


def test_render_odd_meshes_does_not_crash():
    m = trimesh.creation.icosphere(1)
    K = np.array([[50.0, 0, 32], [0, 50, 32], [0, 0, 1]])
    vm = np.eye(4)
    vm[2, 3] = 0.5  # camera inside the sphere: triangles behind it are dropped, no exception
    render_silhouette(m.vertices, m.faces, K, vm, 64, 64)
    behind = np.eye(4)
    behind[2, 3] = -5.0  # the whole mesh behind the camera: empty silhouette
    assert not render_silhouette(m.vertices, m.faces, K, behind, 64, 64).any()

"""The error budget's pure parts on tiny synthetic meshes: the signed closest point, the least-squares removal,
the anchor blend and its oracle fit, the rigid projection, the binning, the wall thickness and the chord."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from benchmarks.bench_inspect_error_budget import (
    binned,
    blend_matrix,
    chord_gap,
    closest_signed_deviation,
    error_stats,
    fit_residual,
    most_oblique_deg,
    neighbour_mean,
    oracle_normal_moves,
    rigid_projector,
    silhouette_views,
    wall_thickness,
)
from reconstruction.inspect import vertex_normals


@pytest.fixture(scope="module")
def sphere():
    m = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def test_closest_signed_deviation_is_positive_outside_and_negative_inside(sphere):
    v, f = sphere
    n = vertex_normals(v, f)
    out = closest_signed_deviation(v - 0.002 * n, n, v, f)
    inside = closest_signed_deviation(v + 0.002 * n, n, v, f)
    assert np.allclose(out, 0.002, atol=2e-4)
    assert np.allclose(inside, -0.002, atol=2e-4)


def test_fit_residual_removes_what_the_basis_spans_and_keeps_the_rest():
    rng = np.random.default_rng(0)
    basis = np.column_stack([np.ones(50), rng.normal(size=50)])
    rest = rng.normal(size=50)
    rest = rest - basis @ np.linalg.lstsq(basis, rest, rcond=None)[0]  # orthogonal to the basis
    values = basis @ [0.3, -2.0] + rest
    assert np.allclose(fit_residual(values, basis), rest)


def test_blend_rows_sum_to_one_and_a_point_on_an_anchor_takes_it_alone(sphere):
    v, _ = sphere
    anchors = v[::7]
    blend = blend_matrix(v, anchors, 4)
    assert blend.shape == (len(v), len(anchors))
    assert np.allclose(np.asarray(blend.sum(1)).ravel(), 1.0, atol=1e-6)
    assert np.isclose(blend[7, 1], 1.0, atol=1e-5)


def test_oracle_fits_any_normal_deviation_when_every_vertex_is_an_anchor(sphere):
    v, f = sphere
    n = vertex_normals(v, f)
    target = 0.001 * np.sin(40.0 * v[:, 0]) * np.cos(30.0 * v[:, 2])
    fit = oracle_normal_moves(blend_matrix(v, v, 4), n, target)
    assert np.abs(fit - target).max() < 1e-6


def test_oracle_with_few_anchors_cannot_follow_fine_detail(sphere):
    v, f = sphere
    n = vertex_normals(v, f)
    target = 0.001 * np.sin(200.0 * v[:, 0])
    fit = oracle_normal_moves(blend_matrix(v, v[::40], 4), n, target)
    assert np.sqrt(np.mean((fit - target) ** 2)) > 0.3 * np.sqrt(np.mean(target**2))


def test_rigid_projector_removes_a_rigid_motion_and_keeps_a_scaling(sphere):
    v, _ = sphere
    anchors = v[::5]
    project = rigid_projector(anchors, np.zeros(3), 0.05)
    translation = np.tile([0.001, -0.002, 0.0005], len(anchors))
    rotation = np.cross([0.0, 0.0, 0.01], anchors).ravel()
    scaling = (0.01 * anchors).ravel()
    assert np.abs(project(translation + rotation)).max() < 1e-12
    assert np.linalg.norm(project(scaling)) > 0.9 * np.linalg.norm(scaling)
    assert np.allclose(project(project(scaling)), project(scaling))


def test_error_stats_are_in_mm_and_in_pixels():
    err = np.array([0.1, -0.2, 0.3, -0.4, np.nan])
    fp = np.array([0.5, 0.5, 0.5, 0.5, 0.5])
    s = error_stats(err, fp)
    assert s["n"] == 4
    assert np.isclose(s["median_mm"], 0.25) and np.isclose(s["median_px"], 0.5)
    assert np.isclose(s["p90_px"], 2.0 * s["p90_mm"])


def test_binned_shares_and_tail():
    err = np.arange(20, dtype=float)  # the tail (above the 90th percentile): the two largest
    key = np.r_[np.zeros(10), np.ones(8), np.full(2, np.nan)]
    rows = binned(err, key, [0, 0.5, 1.5], ["zero", "one", "none"])
    assert [r["share_pct"] for r in rows] == [50.0, 40.0, 10.0]
    assert [r["tail_pct"] for r in rows] == [0.0, 0.0, 100.0]
    assert rows[0]["median_px"] == 4.5


def test_wall_thickness_of_a_slab():
    slab = trimesh.creation.box([0.1, 0.1, 0.02])
    v, f = np.asarray(slab.vertices, np.float64), np.asarray(slab.faces, np.int64)
    top = np.array([[0.01, 0.02, 0.01]])
    assert np.isclose(wall_thickness(top, np.array([[0.0, 0.0, 1.0]]), v, f, 0.5)[0], 0.02)


def test_chord_gap_is_zero_on_a_flat_face_and_the_sagitta_on_a_sphere(sphere):
    plane_v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    plane_f = np.array([[0, 1, 2], [1, 3, 2]])
    assert np.allclose(chord_gap(plane_v, plane_f, plane_v, plane_f), 0.0)
    v, f = sphere
    fine = trimesh.creation.icosphere(subdivisions=5, radius=0.05)
    gap = chord_gap(v, f, np.asarray(fine.vertices), np.asarray(fine.faces))
    centres = v[f].mean(1)
    assert np.allclose(gap, 0.05 - np.linalg.norm(centres, axis=1), atol=2e-5)


def test_neighbour_mean_keeps_a_smooth_field_and_averages_noise_away(sphere):
    v, f = sphere
    n = vertex_normals(v, f)
    smooth = 0.001 * v[:, 2] / 0.05
    noise = 0.001 * np.random.default_rng(1).choice([-1.0, 1.0], len(v))
    assert np.abs(neighbour_mean(v, n, smooth) - smooth).max() < 2e-4
    assert np.std(neighbour_mean(v, n, noise)) < 0.5 * np.std(noise)


def test_neighbour_mean_leaves_out_the_other_wall_of_a_thin_part():
    top = np.array([[x, y, 0.001] for x in range(4) for y in range(4)], float)
    bottom = top * [1.0, 1.0, -1.0]
    points = np.vstack([top, bottom])
    normals = np.vstack([np.tile([0.0, 0.0, 1.0], (16, 1)), np.tile([0.0, 0.0, -1.0], (16, 1))])
    values = np.r_[np.ones(16), -np.ones(16)]
    assert np.allclose(neighbour_mean(points, normals, values, k=8), values)


def test_silhouette_views_counts_the_cameras_that_see_the_point_on_the_outline():
    from calibration.camera import Camera

    K = np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 50.0], [0.0, 0.0, 1.0]])
    c2w = np.eye(4)
    c2w[:3, 3] = [0.0, 0.0, -1.0]  # looking along +z at the origin
    cam = Camera(K, 100, 100, np.zeros(0), c2w)
    points = np.zeros((2, 3))
    normals = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # across the line of sight; facing the camera
    assert silhouette_views(points, normals, [cam, cam]).tolist() == [2, 0]


def test_most_oblique_is_the_largest_angle_among_the_seeing_cameras():
    seen = np.array([[True, False], [True, False], [False, False]])
    cos = np.array([[1.0, 1.0], [0.5, 1.0], [0.0, 1.0]])  # 0, 60 and 90 deg; the third camera does not see vertex 0
    out = most_oblique_deg(seen, cos)
    assert np.isclose(out[0], 60.0) and np.isnan(out[1])

"""Splats on the CAD surface: area-uniform sampling, normal-aligned quats, disk scales, hard meshes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.stats import chisquare

from calibration.camera import look_at_c2w
from calibration.so3 import quat_to_matrix, rotation_between
from reconstruction.splats import (
    DISK_FLATTENING,
    face_areas_normals,
    init_splats,
    knn_indices,
    normals_to_quats,
    project_colors,
    rgb_to_sh_dc,
    sample_surface,
    surface_neighbours,
)
from tests.conftest import require_shared


def box():
    m = trimesh.creation.box(extents=[0.1, 0.2, 0.4])
    return np.asarray(m.vertices), np.asarray(m.faces)


def test_sampling_is_area_uniform_chi_square():
    # Faces of very different areas; the counts per face must follow the area distribution.
    rng = np.random.default_rng(1)
    v = rng.normal(size=(40, 3))
    f = np.array([rng.choice(40, 3, replace=False) for _ in range(30)])
    areas, _ = face_areas_normals(v, f)
    _, fi, bary = sample_surface(v, f, 200_000, np.random.default_rng(0))
    counts = np.bincount(fi, minlength=len(f))
    stat, p = chisquare(counts, areas / areas.sum() * len(fi))
    assert p > 1e-3, (stat, p)
    assert np.all(bary >= -1e-12) and np.allclose(bary.sum(1), 1)
    # Uniform inside a triangle too: each barycentric coordinate has mean 1/3, P(b0 < 1/2) = 3/4.
    np.testing.assert_allclose(bary.mean(0), 1 / 3, atol=0.005)
    assert abs((bary[:, 0] < 0.5).mean() - 0.75) < 0.005


def test_points_lie_on_their_face():
    v, f = box()
    pts, fi, bary = sample_surface(v, f, 500, np.random.default_rng(0))
    np.testing.assert_allclose(pts, np.einsum("nk,nkd->nd", bary, v[f[fi]]), atol=1e-12)


def test_quats_align_local_z_to_normals_including_minus_z():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(1000, 3))
    n = np.concatenate([n, [[0, 0, -1.0], [0, 0, 1.0], [1e-9, 0, -1.0], [0, 1e-13, -1]]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    q = normals_to_quats(n)
    assert np.all(np.isfinite(q))
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1, atol=1e-12)
    r = quat_to_matrix(q)
    np.testing.assert_allclose(r[:, :, 2], n, atol=1e-7)
    # Shortest arc: the same rotation as calibration.so3.rotation_between where that is unique.
    np.testing.assert_allclose(r[:1000], rotation_between(np.tile([0, 0, 1.0], (1000, 1)), n[:1000]), atol=1e-9)


def test_disk_scales_from_three_neighbours():
    # A regular grid with spacing h: the 3 nearest neighbours are at distance h (4 such), so scale = h.
    h = 0.01
    g = np.stack(np.meshgrid(np.arange(20) * h, np.arange(20) * h), -1).reshape(-1, 2)
    v = np.concatenate([g, np.zeros((len(g), 1))], 1)
    from reconstruction.splats import disk_log_scales

    s = disk_log_scales(v)
    corner = np.isin(g[:, 0], [0, 19 * h]) & np.isin(g[:, 1], [0, 19 * h])  # only 2 neighbours at h
    np.testing.assert_allclose(np.exp(s[~corner, 0]), h, rtol=1e-9)
    np.testing.assert_allclose(np.exp(s[~corner, 2]), h * DISK_FLATTENING, rtol=1e-9)
    np.testing.assert_allclose(np.exp(s[corner, 0]), h * (2 + np.sqrt(2)) / 3, rtol=1e-9)
    # Coincident points never give -inf.
    assert np.all(np.isfinite(disk_log_scales(np.zeros((10, 3)))))


def test_init_box_with_12_faces_and_parts():
    v, f = box()
    assert len(f) == 12
    part = (np.arange(12) >= 6).astype(int)
    s = init_splats(v, f, 2000, sh_degree=2, face_part=part, seed=0)
    assert s.means.dtype == np.float32 and s.gaussians.sh.shape == (2000, 9, 3) and s.gaussians.sh_degree == 2
    np.testing.assert_array_equal(s.part_label, part[s.face_index])
    np.testing.assert_allclose(s.gaussians.opacity_logits, 0)  # opacity 0.5
    np.testing.assert_allclose(s.gaussians.sh, 0)  # neutral grey without images
    # Box normals point outwards from the centre.
    centre = v.mean(0)
    assert np.all(np.einsum("nd,nd->n", s.normals, s.means - centre) > 0)
    for arr in (s.means, s.gaussians.quats, s.gaussians.log_scales, s.gaussians.sh):
        assert np.all(np.isfinite(arr))


def test_degenerate_and_zero_area_faces_are_never_sampled():
    v, f = box()
    v = np.concatenate([v, [[0, 0, 0], [1, 1, 1], [2, 2, 2]]])
    bad = np.array([[0, 0, 1], [8, 9, 10], [3, 3, 3]])  # repeated vertex, collinear, a point
    f2 = np.concatenate([bad, f])
    areas, normals = face_areas_normals(v, f2)
    np.testing.assert_array_equal(areas[:3], 0)
    assert np.all(np.isfinite(normals))
    s = init_splats(v, f2, 3000, sh_degree=1, seed=0)
    assert s.face_index.min() >= 3
    with pytest.raises(ValueError, match="zero surface area"):
        init_splats(v, bad, 10, sh_degree=0)


def test_millimetre_mesh_scales_with_units():
    v, f = box()
    s_m = init_splats(v, f, 3000, sh_degree=0, seed=3)
    s_mm = init_splats(v * 1000, f, 3000, sh_degree=0, seed=3)
    np.testing.assert_allclose(s_mm.means, s_m.means * 1000, rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(s_mm.gaussians.log_scales - s_m.gaussians.log_scales, np.log(1000), atol=1e-4)
    np.testing.assert_allclose(s_mm.gaussians.quats, s_m.gaussians.quats, atol=1e-6)


def test_thin_object_scissors():
    path = require_shared("objects", "ycb", "037_scissors", "textured.obj")
    mesh = trimesh.load(path, force="mesh", process=False)
    s = init_splats(mesh.vertices, mesh.faces, 20_000, sh_degree=1, seed=0)
    for arr in (s.means, s.gaussians.quats, s.gaussians.log_scales, s.normals):
        assert np.all(np.isfinite(arr))
    # Splats are disks far smaller than the object (a few millimetres on a ~0.2 m object).
    assert np.exp(s.gaussians.log_scales[:, 0]).max() < 0.01
    r = quat_to_matrix(s.gaussians.quats)
    np.testing.assert_allclose(r[:, :, 2], s.normals, atol=1e-5)


def test_project_colors_picks_visible_side():
    # A two-sided plate seen from +z: top splats get the image colour, the hidden bottom stays grey.
    n = 400
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.05, 0.05, size=(n, 2))
    top = np.concatenate([xy, np.full((n, 1), 0.001)], 1)
    bottom = np.concatenate([xy, np.full((n, 1), -0.001)], 1)
    means = np.concatenate([top, bottom])
    normals = np.concatenate([np.tile([0, 0, 1.0], (n, 1)), np.tile([0, 0, -1.0], (n, 1))])
    c2w = look_at_c2w(np.array([0, 0, 0.5]), np.zeros(3), up=np.array([0, 1.0, 0]))
    viewmat = np.linalg.inv(c2w)
    K = np.array([[200.0, 0, 32], [0, 200, 32], [0, 0, 1]])
    img = np.zeros((1, 64, 64, 3), np.float32)
    img[..., 0] = 1.0
    rgb = project_colors(means, normals, img, np.ones((1, 64, 64), bool), viewmat[None], K[None])
    np.testing.assert_allclose(rgb[:n], [[1, 0, 0]] * n)
    np.testing.assert_allclose(rgb[n:], 0.5)
    np.testing.assert_allclose(rgb_to_sh_dc(np.array([0.5])), 0)


def test_knn_excludes_self():
    pts = np.random.default_rng(0).normal(size=(100, 3))
    idx = knn_indices(pts, 20)
    assert idx.shape == (100, 20)
    assert not np.any(idx == np.arange(100)[:, None])
    assert knn_indices(pts[:5], 20).shape == (5, 4)


def thin_wall(gap: float, n: int = 12):
    """Two n x n grids of unit spacing, `gap` apart, with outward normals: the faces of a thin wall."""
    g = np.stack(np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float)), -1).reshape(-1, 2)
    top, bottom = np.c_[g, np.full(len(g), gap / 2)], np.c_[g, np.full(len(g), -gap / 2)]
    normals = np.r_[np.tile([0.0, 0.0, 1.0], (len(g), 1)), np.tile([0.0, 0.0, -1.0], (len(g), 1))]
    return np.r_[top, bottom], normals


def test_surface_neighbours_stay_on_their_face_of_a_thin_wall():
    pts, normals = thin_wall(gap=0.5)
    half = len(pts) // 2
    knn = knn_indices(pts, 8)
    assert (knn[:half] >= half).any()  # in space, some of the 8 nearest are across the wall
    nb = surface_neighbours(pts, normals, 8)
    assert nb.shape == (len(pts), 8)
    # The same nearest points, those across the wall dropped (not replaced by farther ones on this side).
    across = (knn >= half) != (np.arange(len(pts)) >= half)[:, None]
    np.testing.assert_array_equal(nb, np.where(across, -1, knn))
    assert (nb >= 0).any(1).all()
    # On one face alone they are the plain nearest neighbours.
    one, up = pts[:half], normals[:half]
    np.testing.assert_array_equal(surface_neighbours(one, up, 8), knn_indices(one, 8))
    assert surface_neighbours(pts[:3], normals[:3], 8).shape == (3, 2)
    assert surface_neighbours(pts[:1], normals[:1], 8).shape == (1, 0)


def test_initial_opacity_is_stored_as_a_logit():
    v, f = box()
    s = init_splats(v, f, 500, sh_degree=0, opacity=0.9, seed=0)
    np.testing.assert_allclose(1 / (1 + np.exp(-s.gaussians.opacity_logits)), 0.9, rtol=1e-6)
    for bad in (0.0, 1.0, 1.5):
        with pytest.raises(ValueError, match="opacity"):
            init_splats(v, f, 10, sh_degree=0, opacity=bad)


def test_alpha_half_reach_follows_the_gaussian_falloff():
    from reconstruction.gaussians import Gaussians
    from reconstruction.splats import alpha_half_reach

    sigma = 0.002
    log_scales = np.log(np.array([[sigma, sigma, 1e-5], [sigma, sigma, 1e-5]]))
    logits = np.log(np.array([0.9 / 0.1, 0.4 / 0.6]))  # opacities 0.9 and 0.4
    g = Gaussians.from_arrays(np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1)), log_scales, logits, np.zeros((2, 1, 3)))
    reach = alpha_half_reach(g)
    assert np.isclose(reach[0], sigma * np.sqrt(2 * np.log(1.8)), rtol=1e-6)
    # Exactly where alpha is 1/2:
    assert np.isclose(0.9 * np.exp(-(reach[0] ** 2) / (2 * sigma**2)), 0.5, rtol=1e-6)
    assert reach[1] == 0.0  # never reaches alpha 1/2

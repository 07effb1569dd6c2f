"""Inspection arithmetic: signs, units, the far wall of thin parts, visibility, and the verdict's codes."""

import numpy as np
import pytest
import trimesh

from calibration.camera import Camera, look_at_c2w
from reconstruction.inspect import (
    EXIT_CODES,
    EXIT_NEAR_TOLERANCE,
    MIN_SIN,
    Inspection,
    inspect_meshes,
    line_deviation,
    local_fit_residual,
    part_reports,
    point_visibility,
    projection_sigma,
    rasterize_mesh,
    surface_distance,
    tolerance_calls,
    verdict,
    vertex_normals,
)
from reconstruction.inspect_silhouette import signed_distance


def sphere(radius=0.05, subdivisions=3):
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def camera_at(eye, target=(0.0, 0.0, 0.0), size=(160, 120), f=150.0):
    w, h = size
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    return Camera(K, w, h, np.zeros(0), look_at_c2w(np.asarray(eye, float), np.asarray(target, float)))


def ring(n=8, distance=0.4, elevations=(-35.0, 35.0)):
    cams = []
    for el in np.radians(elevations):
        for az in np.linspace(0, 2 * np.pi, n, endpoint=False):
            cams.append(camera_at(distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])))
    return cams


def test_normals_point_outward_even_for_an_inside_out_mesh():
    v, f = sphere()
    radial = v / np.linalg.norm(v, axis=1, keepdims=True)
    assert np.einsum("ij,ij->i", vertex_normals(v, f), radial).min() > 0.99
    assert np.einsum("ij,ij->i", vertex_normals(v, f[:, ::-1]), radial).min() > 0.99


@pytest.mark.parametrize("delta_m, expected_mm", [(0.001, 1.0), (-0.002, -2.0)])
def test_deviation_is_signed_along_the_outward_normal_in_millimetres(delta_m, expected_mm):
    v, f = sphere()
    grown = v * (1 + delta_m / 0.05)  # every vertex moved radially by delta_m metres
    insp = inspect_meshes(v, f, np.zeros(len(f), np.int64), ["ball"], grown, f, ring())
    # Vertex normals of a tessellated sphere are radial to within a fraction of a degree.
    np.testing.assert_allclose(insp.deviation_mm, expected_mm, atol=2e-3 * abs(expected_mm))
    np.testing.assert_allclose(insp.area_mm2.sum(), trimesh.Trimesh(v, f).area * 1e6)
    np.testing.assert_allclose(insp.vertices_mm, v * 1000)


def test_a_surface_that_is_not_the_moved_cad_is_found_along_the_normal():
    v, f = sphere(subdivisions=3)
    other_v, other_f = sphere(radius=0.0515, subdivisions=4)  # a different tessellation, 1.5 mm outside
    insp = inspect_meshes(v, f, np.zeros(len(f), np.int64), ["ball"], other_v, other_f, ring())
    # A chord of the finer sphere lies up to r(1 - cos(edge/2r)) inside it: about 0.1 mm here.
    assert np.all(np.abs(insp.deviation_mm - 1.5) < 0.15)
    assert insp.unseen_pct() < 5.0


def test_the_far_wall_of_a_thin_part_is_never_taken_for_its_surface():
    plate = trimesh.creation.box(extents=[0.1, 0.1, 0.002])
    top = np.array([[0.01, 0.02, 0.001]])
    up = np.array([[0.0, 0.0, 1.0]])
    lifted = plate.vertices + [0, 0, 0.0005]
    # The lifted top is 0.5 mm out; the bottom wall, 1.5 mm in, faces the other way and is ignored.
    np.testing.assert_allclose(line_deviation(top, up, lifted, plate.faces, 0.01), [0.0005])
    sunk = plate.vertices - [0, 0, 0.0015]
    np.testing.assert_allclose(line_deviation(top, up, sunk, plate.faces, 0.01), [-0.0015])
    assert np.isnan(line_deviation(top, up, plate.vertices + [0, 0, 0.02], plate.faces, 0.01))[0]


def test_surface_distance_is_the_exact_point_to_triangle_distance():
    tri_v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    tri_f = np.array([[0, 1, 2]])
    pts = np.array([[0.2, 0.2, 0.3], [2.0, 0.0, 0.0], [-1.0, -1.0, 0.0], [1.0, 1.0, 0.0]])
    np.testing.assert_allclose(surface_distance(pts, tri_v, tri_f), [0.3, 1.0, np.sqrt(2), np.sqrt(0.5)])


def test_zbuffer_depth_matches_the_surface():
    v, f = sphere(radius=0.05, subdivisions=4)
    cam = camera_at([0, 0, 0.4])
    depth, face, bary = rasterize_mesh(v, f, cam)
    centre = depth[60, 80]
    assert face[60, 80] >= 0 and abs(centre - 0.35) < 2e-4
    assert np.isinf(depth[0, 0]) and face[0, 0] == -1
    np.testing.assert_allclose(bary[face >= 0].sum(1), 1.0)


def test_visibility_counts_views_and_hides_what_is_behind_or_occluded():
    v, f = sphere()
    n = vertex_normals(v, f)
    cam = camera_at([0, 0, 0.4])
    vis = point_visibility(v, n, v, f, [cam])
    facing = n[:, 2]
    assert vis.seen[0][facing > 0.5].all() and not vis.seen[0][facing < 0].any()
    top = int(np.argmax(v[:, 2]))
    assert vis.views[top] == 1 and vis.best_angle_deg[top] < 1.0
    assert np.isnan(vis.best_angle_deg[int(np.argmin(v[:, 2]))])
    # A second ball between the camera and the first hides the first one's top.
    blocker = v * 0.5 + [0, 0, 0.15]
    both_v = np.concatenate([v, blocker])
    both_f = np.concatenate([f, f + len(v)])
    vis = point_visibility(v, n, both_v, both_f, [cam])
    assert not vis.seen[0, top]


def _inspection(deviation, views, part=None, names=("a",), uncertainty=None):
    deviation = np.asarray(deviation, float)
    k = len(deviation)
    return Inspection(
        vertices_mm=np.arange(3 * k, dtype=float).reshape(k, 3),
        deviation_mm=deviation,
        views=np.asarray(views),
        best_angle_deg=np.where(np.asarray(views) > 0, 10.0, np.nan),
        area_mm2=np.ones(k),
        part=np.zeros(k, np.int64) if part is None else np.asarray(part),
        part_names=list(names),
        uncertainty_mm=None if uncertainty is None else np.asarray(uncertainty, float),
    )


def test_unseen_surface_in_no_cameras_view_is_told_apart_from_surface_hidden_by_the_part():
    # Two nested spheres seen by cameras on a ring above the equator: the outer sphere's underside is in no
    # camera's view; the inner sphere faces the cameras but the outer one hides it.
    v, f = sphere()
    both_v, both_f = np.concatenate([v, 0.5 * v]), np.concatenate([f, f + len(v)])
    cams = ring(elevations=(40.0,))
    vis = point_visibility(both_v, vertex_normals(both_v, both_f), both_v, both_f, cams)
    outer, inner = np.arange(len(v)), np.arange(len(v), 2 * len(v))
    below = outer[v[:, 2] < -0.045]
    assert below.size and not vis.in_view[below].any() and not vis.views[below].any()
    assert not vis.views[inner].any() and (vis.in_view[inner] > 0).mean() > 0.5
    assert np.all(vis.in_view >= vis.views)
    insp = inspect_meshes(both_v, both_f, np.zeros(len(both_f), np.int64), ["ball"], both_v, both_f, cams)
    assert 0 < insp.out_of_view_pct() < insp.unseen_pct()
    unsure = verdict(insp, 1.0, 10.0)
    assert unsure.line.startswith(
        f"UNCERTAIN {insp.unseen_pct():.0f} % of the surface unseen ({insp.out_of_view_pct():.0f} % in no camera's view)"
    )
    assert unsure.out_of_view_pct == insp.out_of_view_pct()


def test_verdict_lines_and_exit_codes():
    ok = verdict(_inspection([0.2, -0.8, 0.5, 0.1], [2, 3, 1, 4]), 1.0, 25.0)
    assert (ok.status, ok.exit_code, ok.line) == ("PASS", 0, "PASS max 0.8 mm (tolerance 1 mm)")
    bad = verdict(_inspection([0.2, -2.3, 0.5, 0.1], [2, 3, 1, 4], part=[0, 1, 1, 0], names=("body", "jaw")), 1.0, 25.0)
    assert (bad.status, bad.exit_code, bad.part) == ("FAIL", 1, "jaw")
    assert bad.line == "FAIL part 'jaw' -2.3 mm at (3.0, 4.0, 5.0) mm"
    assert EXIT_CODES == {"PASS": 0, "FAIL": 1, "UNCERTAIN": 3}
    # A deviation that rounds onto the tolerance is printed to a hundredth: 1.0 mm would read as within 1 mm.
    assert verdict(_inspection([0.2, -0.98, 0.5], [2, 3, 1]), 1.0, 25.0).line == "PASS max 0.98 mm (tolerance 1 mm)"
    assert verdict(_inspection([0.2, 1.04, 0.5], [2, 3, 1]), 1.0, 25.0).line.startswith("FAIL part 'a' +1.04 mm at (")


def test_unseen_surface_is_never_in_tolerance_and_never_fails():
    # The 9 mm vertex is unseen: it neither fails the part nor counts as measured.
    insp = _inspection([0.2, 9.0, 0.5, 0.1], [2, 0, 1, 4])
    assert verdict(insp, 1.0, 30.0).line == "PASS max 0.5 mm (tolerance 1 mm), 25 % of the surface unseen"
    unsure = verdict(insp, 1.0, 20.0)
    assert (unsure.status, unsure.exit_code) == ("UNCERTAIN", 3)
    assert unsure.line.startswith("UNCERTAIN 25 % of the surface unseen")
    # A share that rounds onto the limit it is judged against is printed to a tenth: 25 % would read as within 25 %.
    assert verdict(insp, 1.0, 24.9).line.startswith("UNCERTAIN 25.0 % of the surface unseen")
    assert verdict(insp, 1.0, 25.0).line.startswith("PASS") and verdict(insp, 1.0, 25.0).line.endswith(", 25 % of the surface unseen")
    blind = verdict(_inspection([0.0, 0.0], [0, 0]), 1.0, 100.0)
    assert blind.status == "UNCERTAIN" and blind.max_abs_mm is None
    # A seen vertex out of tolerance fails even when much of the surface is unseen.
    assert verdict(_inspection([3.0, 0.0, 0.0], [1, 0, 0]), 1.0, 10.0).status == "FAIL"
    with pytest.raises(ValueError, match="tolerance"):
        verdict(insp, 0.0, 10.0)


def test_part_reports_keep_unseen_parts_apart():
    insp = _inspection([0.4, -1.5, 7.0, 7.0], [1, 2, 0, 0], part=[0, 0, 1, 1], names=("body", "hidden"))
    body, hidden = part_reports(insp, 1.0)
    assert body.worst_mm == -1.5 and body.worst_at_mm == (3.0, 4.0, 5.0) and body.out_of_tolerance_pct == 50.0
    assert body.unseen_pct == 0.0 and body.single_view_pct == 50.0 and body.views_median == 1.5
    assert hidden.worst_mm is None and hidden.unseen_pct == 100.0 and hidden.out_of_tolerance_pct == 0.0
    assert hidden.views_median is None and hidden.single_view_pct == 0.0


def test_pass_needs_every_seen_vertex_inside_the_tolerance_by_more_than_its_uncertainty():
    ok = verdict(_inspection([0.2, -0.7, 0.5, 9.0], [2, 3, 1, 0], uncertainty=[0.1, 0.25, 0.3, np.nan]), 1.0, 30.0)
    assert (ok.status, ok.exit_code, ok.straddling) == ("PASS", 0, ())
    assert ok.line == "PASS max 0.7 +-0.25 mm (tolerance 1 mm), 25 % of the surface unseen"
    # The same map with one vertex's uncertainty reaching the tolerance: UNCERTAIN, and that vertex is named.
    near = verdict(
        _inspection([0.2, -0.7, 0.5, 9.0], [2, 3, 1, 0], part=[0, 1, 0, 1], names=("body", "jaw"), uncertainty=[0.1, 0.35, 0.3, np.nan]),
        1.0,
        30.0,
    )
    assert (near.status, near.exit_code, near.reason) == ("UNCERTAIN", EXIT_NEAR_TOLERANCE, "near tolerance")
    assert [v.vertex for v in near.straddling] == [1] and near.straddling[0].part == "jaw"
    assert near.line == (
        "UNCERTAIN 1 seen vertices (25.0 % of the surface) lie within their uncertainty of the 1 mm tolerance: "
        "vertex 1 of part 'jaw' -0.70 +-0.35 mm at (3.0, 4.0, 5.0) mm"
    )
    assert near.to_dict()["straddling"] == [
        {"vertex": 1, "part": "jaw", "deviation_mm": -0.7, "uncertainty_mm": 0.35, "at_mm": [3.0, 4.0, 5.0]}
    ]
    # Beyond the tolerance but within its uncertainty of it: not a FAIL, the vertex is named.
    over = verdict(_inspection([1.2, 0.1], [2, 2], uncertainty=[0.3, 0.1]), 1.0, 25.0)
    assert over.status == "UNCERTAIN" and [v.vertex for v in over.straddling] == [0]


def test_an_uncertain_line_names_the_largest_deviations_first_and_counts_the_rest():
    dev = [0.95, -1.05, 0.9, 1.1, 0.97, -0.99, 0.92, 0.0]
    insp = _inspection(dev, [1] * 8, uncertainty=[0.2] * 8)
    v = verdict(insp, 1.0, 25.0)
    assert [x.vertex for x in v.straddling] == [3, 1, 5, 4, 0, 6, 2]
    assert v.line.count("vertex ") == 5 and v.line.endswith("; and 2 more") and v.straddling_pct == 700 / 8


def test_fail_needs_a_departure_beyond_the_tolerance_plus_its_uncertainty_and_names_the_worst():
    insp = _inspection(
        [0.2, 1.6, -3.0, 2.2, 0.1], [2, 2, 1, 3, 2], part=[0, 0, 1, 0, 0], names=("body", "jaw"), uncertainty=[0.1, 0.8, 0.5, 0.4, 0.1]
    )
    bad = verdict(insp, 1.0, 25.0)
    # Vertex 1 (1.6 +-0.8) straddles; 2 and 3 are out beyond doubt; the worst of those, the jaw's -3.0, is named.
    assert (bad.status, bad.exit_code, bad.part, bad.deviation_mm, bad.uncertainty_mm) == ("FAIL", 1, "jaw", -3.0, 0.5)
    assert bad.line == "FAIL part 'jaw' -3.0 +-0.50 mm at (6.0, 7.0, 8.0) mm; 40 % of the surface out of tolerance beyond its uncertainty"
    assert bad.out_pct == 40.0 and [x.vertex for x in bad.straddling] == [1]
    # An uncertain vertex larger than every certain one is not what FAIL names: it is not known to be out.
    worse = verdict(_inspection([5.0, 1.6], [1, 1], uncertainty=[4.5, 0.1]), 1.0, 25.0)
    assert worse.status == "FAIL" and worse.deviation_mm == 1.6


def test_too_much_unseen_keeps_exit_3_even_where_a_seen_vertex_straddles():
    v = verdict(_inspection([0.9, 0.0, 0.0, 0.0], [1, 0, 0, 1], uncertainty=[0.3, np.nan, np.nan, 0.1]), 1.0, 25.0)
    assert (v.status, v.exit_code, v.reason) == ("UNCERTAIN", 3, "unseen") and [x.vertex for x in v.straddling] == [0]
    assert EXIT_CODES["UNCERTAIN"] == 3 and EXIT_NEAR_TOLERANCE == 4


def test_tolerance_calls_on_the_boundaries():
    out, straddle = tolerance_calls(np.array([1.5, -1.5, 0.5, 0.5, 1.0]), np.array([0.4, 0.5, 0.4, 0.5, np.nan]), 1.0)
    assert out.tolist() == [True, False, False, False, False]
    assert straddle.tolist() == [False, True, False, True, True]


def test_projection_sigma_from_angles_pixel_size_and_views():
    fp = np.array([[0.001, 0.001]])
    # Looking across the surface a view places it to sigma_px pixels; along the normal only through MIN_SIN.
    np.testing.assert_allclose(projection_sigma(np.array([[True, True]]), np.array([[0.0, 1.0]]), fp, 0.5), [0.0005, 0.0005 / MIN_SIN])
    # Twice the pixel size, twice the uncertainty; the best view decides (one fit explains them all: no 1/sqrt(n)
    # from views that share its errors); an unseen point has none.
    two = projection_sigma(
        np.array([[True], [True], [False]]), np.array([[0.0], [0.8], [0.0]]), np.array([[0.002], [0.001], [0.0001]]), 0.5
    )
    np.testing.assert_allclose(two, [0.5 * 0.001 / 0.6])
    assert np.isnan(projection_sigma(np.array([[False]]), np.zeros((1, 1)), fp[:, :1], 0.5))[0]


def test_local_fit_residual_is_zero_on_a_plane_and_the_noise_on_a_noisy_map():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-1, 1, (400, 2))
    pts = np.column_stack([xy, np.zeros(400)])
    up = np.tile([0.0, 0.0, 1.0], (400, 1))
    valid = np.ones(400, bool)
    assert np.nanmax(local_fit_residual(pts, up, 0.3 + 0.2 * xy[:, 0] - 0.1 * xy[:, 1], valid)) < 1e-9
    noisy = local_fit_residual(pts, up, 0.01 * rng.standard_normal(400), valid, k=30)
    assert 0.007 < np.median(noisy) < 0.013
    valid[:10] = False
    assert np.isnan(local_fit_residual(pts, up, np.zeros(400), valid)[:10]).all()


def test_seen_vertices_carry_an_uncertainty_that_grows_with_the_pixel_size():
    v, f = sphere()
    near = inspect_meshes(v, f, np.zeros(len(f), np.int64), ["ball"], v, f, ring(distance=0.3, elevations=(40.0,)))
    far = inspect_meshes(v, f, np.zeros(len(f), np.int64), ["ball"], v, f, ring(distance=0.6, elevations=(40.0,)))
    for insp in (near, far):
        assert np.isfinite(insp.uncertainty_mm[insp.seen]).all() and np.isnan(insp.uncertainty_mm[~insp.seen]).all()
    both = near.seen & far.seen
    # Twice the camera distance: the pixel at the ball is (0.6 - r) / (0.3 - r) as large, and so is the uncertainty.
    ratio = (0.6 - 0.05) / (0.3 - 0.05)
    np.testing.assert_allclose(np.median(far.footprint_mm[both] / near.footprint_mm[both]), ratio, rtol=0.05)
    np.testing.assert_allclose(np.median(far.uncertainty_mm[both] / near.uncertainty_mm[both]), ratio, rtol=0.1)


def test_masks_at_the_cameras_own_resolution_correct_the_map_to_a_fraction_of_a_pixel():
    v, f = sphere(subdivisions=3)
    cams = ring()  # 160x120: a pixel is about 2.4 mm at the ball
    truth = trimesh.creation.icosphere(subdivisions=5, radius=0.0508)  # the part is 0.8 mm larger than its twin
    masks = [rasterize_mesh(truth.vertices, truth.faces, c.scaled(320, 240))[1] >= 0 for c in cams]
    plain = inspect_meshes(v, f, np.zeros(len(f), np.int64), ["ball"], v, f, cams)
    refined = inspect_meshes(v, f, np.zeros(len(f), np.int64), ["ball"], v, f, cams, masks=masks)
    assert np.nanmedian(np.abs(plain.deviation_mm - 0.8)) > 0.7
    assert np.nanmedian(np.abs(refined.deviation_mm[refined.seen] - 0.8)) < 0.15


def test_the_signed_distance_field_crosses_zero_on_the_pixel_edge():
    mask = np.zeros((5, 8), bool)
    mask[:, :4] = True
    np.testing.assert_allclose(signed_distance(mask)[2], [-3.5, -2.5, -1.5, -0.5, 0.5, 1.5, 2.5, 3.5])


def ellipsoid(subdivisions=4):
    """A part with no symmetry a rigid motion could hide in: semi-axes 50, 35, 25 mm (metres)."""
    v, f = sphere(radius=1.0, subdivisions=subdivisions)
    return v * [0.05, 0.035, 0.025], f


def moved_by(v, rotvec_deg, translation_m, scale=1.0):
    from scipy.spatial.transform import Rotation

    return scale * v @ Rotation.from_rotvec(rotvec_deg, degrees=True).as_matrix().T + translation_m


def test_where_a_loose_part_lies_is_taken_out_and_its_dent_is_measured_in_full():
    v, f = ellipsoid()
    normals = vertex_normals(v, f)
    dent_at = np.argmax(v[:, 2])  # the top, which the ring sees
    push = 0.002 * np.clip(1 - np.linalg.norm(v - v[dent_at], axis=1) / 0.012, 0, None)
    part = moved_by(v - push[:, None] * normals, [2.0, -1.0, 1.5], [0.0015, -0.001, 0.0005])
    plain = inspect_meshes(v, f, np.zeros(len(f), np.int64), ["egg"], part, f, ring(), best_fit=None)
    insp = inspect_meshes(v, f, np.zeros(len(f), np.int64), ["egg"], part, f, ring())
    far = insp.seen & (push == 0)
    # As it lies, the part reads millimetres off everywhere; aligned, only the dent departs, by its full depth.
    assert np.abs(plain.deviation_mm[far]).max() > 1.0
    assert np.abs(insp.deviation_mm[far]).max() < 0.05
    np.testing.assert_allclose(insp.deviation_mm[dent_at], -2.0, atol=0.05)
    # The motion it took out is the inverse of the one that moved the part (to within the dent's pull on it).
    np.testing.assert_allclose(np.linalg.norm(insp.alignment.rotation_deg), np.linalg.norm([2.0, -1.0, 1.5]), atol=0.05)
    assert insp.alignment.kind == "rigid" and insp.alignment.scale == 0.0


def test_a_part_larger_than_its_drawing_reads_its_size_on_a_metric_rig_and_nothing_where_scale_is_unknown():
    v, f = ellipsoid(subdivisions=3)
    grown = moved_by(v, [0.5, 0.0, 0.0], [0.0, 0.0, 0.001], scale=1.01)
    rigid = inspect_meshes(v, f, np.zeros(len(f), np.int64), ["egg"], grown, f, ring())
    similarity = inspect_meshes(v, f, np.zeros(len(f), np.int64), ["egg"], grown, f, ring(), best_fit="similarity")
    # 1 % of 25-50 mm semi-axes: 0.25-0.5 mm out, everywhere; a similarity takes it out as placement and size.
    assert 0.2 < np.median(rigid.deviation_mm[rigid.seen]) < 0.55
    assert np.abs(similarity.deviation_mm[similarity.seen]).max() < 0.02
    np.testing.assert_allclose(similarity.alignment.scale, 0.01, atol=5e-4)
    with pytest.raises(ValueError, match="rigid, similarity"):
        inspect_meshes(v, f, np.zeros(len(f), np.int64), ["egg"], grown, f, ring(), best_fit="affine")


def test_a_twin_whose_rig_has_no_metric_scale_is_aligned_by_a_similarity():
    from types import SimpleNamespace

    from reconstruction.inspect import alignment_kind

    assert alignment_kind(SimpleNamespace(training={"inputs": {"metric": True}})) == "rigid"
    assert alignment_kind(SimpleNamespace(training={"inputs": {"metric": False}})) == "similarity"
    assert alignment_kind(SimpleNamespace(training={})) == "rigid"

"""The twin's surface: out to the splats' alpha-1/2 reach, and no face folded through another."""

from __future__ import annotations

import numpy as np
import trimesh

from reconstruction.gaussians import Gaussians
from reconstruction.splats import alpha_half_reach
from reconstruction.surface import self_intersecting_faces, silhouette_surface, untangle


def test_silhouette_surface_moves_a_sphere_out_by_the_reach_whatever_its_winding():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    pts = np.asarray(sphere.vertices)
    n = len(pts)
    log_scales = np.log(np.tile([0.001, 0.001, 1e-5], (n, 1)))
    g = Gaussians.from_arrays(pts, np.tile([1.0, 0, 0, 0], (n, 1)), log_scales, np.full(n, np.log(9.0)), np.zeros((n, 1, 3)))
    reach = float(alpha_half_reach(g)[0])
    for faces in (sphere.faces, sphere.faces[:, ::-1]):
        moved = silhouette_surface(pts, faces, g)
        np.testing.assert_allclose(np.linalg.norm(moved, axis=1), 0.05 + reach, rtol=1e-3)


def test_crossing_faces_are_found_and_touching_ones_are_not():
    ball = trimesh.creation.icosphere(subdivisions=2)
    assert not self_intersecting_faces(ball.vertices, ball.faces).any()  # neighbours share edges only
    box = trimesh.creation.box()
    two = np.vstack([box.vertices, box.vertices + 0.3]), np.vstack([box.faces, box.faces + 8])
    crossing = self_intersecting_faces(*two)
    assert crossing.any() and not crossing.all()  # the far faces of each box cross nothing
    assert not self_intersecting_faces(np.zeros((0, 3)), np.zeros((0, 3), np.int64)).any()


def slab(thickness: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """A finely triangulated 1 x 1 x thickness box: vertices [V, 3], faces [F, 3]."""
    box = trimesh.creation.box((1.0, 1.0, thickness))
    v, f = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=0.1)
    return np.asarray(v, np.float64), np.asarray(f, np.int64)


def test_a_patch_pushed_through_the_far_wall_is_undone_and_the_rest_keeps_its_move():
    rest, faces = slab()
    moved = rest + [0.0, 0.0, 0.001]  # everything moves a little
    top = rest[:, 2] > 0
    patch = top & (np.linalg.norm(rest[:, :2], axis=1) < 0.2)
    moved[patch, 2] -= 0.05  # the top pushed through the bottom: a fold
    assert (self_intersecting_faces(moved, faces)).any()
    out, untangled = untangle(rest, moved, faces)
    assert not self_intersecting_faces(out, faces).any()
    far = np.linalg.norm(rest[:, :2], axis=1) > 0.5
    assert not untangled[far].any() and np.allclose(out[far], moved[far])  # nothing far from the fold changed
    assert untangled[patch].all()


def test_a_fold_in_a_part_carried_sideways_keeps_the_carry():
    # A thin part the fit carried 0.1 sideways, with a patch of its top pushed through its bottom on the way (the
    # rig scenes' spatula neck): the fold goes, the carry stays; pulling back towards rest would undo both.
    rest, faces = slab()
    moved = rest + [0.1, 0.0, 0.0]
    patch = (rest[:, 2] > 0) & (np.linalg.norm(rest[:, :2], axis=1) < 0.2)
    moved[patch, 2] -= 0.03
    assert (self_intersecting_faces(moved, faces)).any()
    out, untangled = untangle(rest, moved, faces)
    assert not self_intersecting_faces(out, faces).any() and untangled[patch].all()
    np.testing.assert_allclose(out[:, 0] - rest[:, 0], 0.1, atol=1e-9)


def test_a_rest_surface_that_crosses_itself_is_not_blamed_on_the_move():
    box = trimesh.creation.box()
    rest = np.vstack([box.vertices, box.vertices + 0.3])
    faces = np.vstack([box.faces, box.faces + 8])
    out, untangled = untangle(rest, rest * 1.01, faces)
    assert not untangled.any() and np.allclose(out, rest * 1.01)


def _ball_and_cameras():
    from calibration.camera import Camera, look_at_c2w

    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    K = np.array([[400.0, 0, 160], [0, 400.0, 120], [0, 0, 1]])
    cams = [
        Camera(K, 320, 240, c2w=look_at_c2w(np.array(eye, float), np.zeros(3)))
        for eye in ([0.3, 0, 0.05], [0, 0.3, -0.05], [-0.2, -0.2, 0.1])
    ]
    return np.asarray(ball.vertices), np.asarray(ball.faces), cams


def test_the_mask_step_finds_how_far_the_masks_reach_past_the_mesh():
    from reconstruction.mesh_raster import rasterize_mesh
    from reconstruction.surface import mask_overlap_offset

    v, f, cams = _ball_and_cameras()
    masks = np.stack([rasterize_mesh(v * 1.04, f, cam)[1] >= 0 for cam in cams])  # the object is 2 mm larger all round
    step = mask_overlap_offset(v, f, cams, masks, bracket=0.005)
    assert abs(step - 0.002) < 0.0002  # a tenth of a millimetre: a fraction of the 0.7 mm pixel there
    assert mask_overlap_offset(v, f, cams, np.ones_like(masks), bracket=0.005) > 0.0049  # masks that cover everything: the bracket
    out_of_view = v + [0.0, 0.0, 5.0]
    assert mask_overlap_offset(out_of_view, f, cams, masks, bracket=0.005) == 0.0  # nothing to overlap: nothing moves


def test_a_local_excess_does_not_shrink_the_rest_of_the_surface():
    from reconstruction.mesh_raster import rasterize_mesh
    from reconstruction.surface import mask_overlap_offset

    v, f, cams = _ball_and_cameras()
    masks = np.stack([rasterize_mesh(v, f, cam)[1] >= 0 for cam in cams])  # the object: the ball alone
    # The mesh: the ball, right, plus a knob the object lacks. Matching the masks' areas would take the knob's
    # area off the whole ball's outline (about 1 mm inwards); the best overlap leaves the ball where it is.
    knob = v * 0.3 + [0.0, 0.0, 0.05]
    with_knob_v, with_knob_f = np.vstack([v, knob]), np.vstack([f, f + len(v)])
    assert abs(mask_overlap_offset(with_knob_v, with_knob_f, cams, masks, bracket=0.005)) < 0.0002


def test_a_face_that_crossed_in_rest_is_still_untangled_from_a_new_one():
    # G crosses H in rest (allowed: the CAD's own); the move takes G through T as well, which is new.
    g = [[0.0, -1, -1], [0, 1, -1], [0, 0, 1]]
    h = [[-1.0, 0, 0], [0.2, 0, 0.2], [0.2, 0.1, -0.2]]
    t = [[0.5, -1, -1], [0.5, 1, -1], [0.5, 0, 1]]
    rest, faces = np.array(g + h + t), np.arange(9).reshape(3, 3)
    moved = rest.copy()
    moved[:3] = [[0.3, -1, -1], [0.3, 1, -1], [0.7, 0, 0.5]]
    out, untangled = untangle(rest, moved, faces)
    assert not self_intersecting_faces(out, faces)[2]
    assert untangled.tolist() == [True] * 3 + [False] * 6  # only G's move changed


def test_untangled_names_only_the_vertices_whose_move_changed():
    rest, faces = slab()
    moved = rest + [0.1, 0.0, 0.0]
    patch = (rest[:, 2] > 0) & (np.linalg.norm(rest[:, :2], axis=1) < 0.2)
    moved[patch, 2] -= 0.03
    out, untangled = untangle(rest, moved, faces)
    assert np.array_equal(untangled, np.any(out - rest != moved - rest, axis=1))


def test_the_neighbour_mean_keeps_a_lone_vertex_and_ignores_degenerate_edges():
    from reconstruction.surface import vertex_neighbour_mean

    mean = vertex_neighbour_mean(np.array([[0, 1, 2], [0, 0, 1]]), 4).toarray()
    np.testing.assert_allclose(mean.sum(axis=1), 1.0)
    assert mean[3, 3] == 1.0 and mean[0, 0] == 0.0  # vertex 3 is on no face; [0, 0, 1] adds no self-edge
    assert vertex_neighbour_mean(np.zeros((0, 3), np.int64), 2).toarray().tolist() == [[1.0, 0.0], [0.0, 1.0]]


def test_the_mask_step_takes_views_of_mixed_sizes_on_one_canvas():
    from calibration.camera import Camera
    from reconstruction.mesh_raster import rasterize_mesh
    from reconstruction.surface import mask_overlap_offset

    v, f, cams = _ball_and_cameras()
    cams[1] = Camera(cams[1].K, 320, 200, c2w=cams[1].c2w)  # one portrait-cropped view, top-left on the 320x240 canvas
    masks = np.zeros((3, 240, 320), bool)
    for m, cam in zip(masks, cams):
        m[: cam.height, : cam.width] = rasterize_mesh(v * 1.04, f, cam)[1] >= 0
    assert abs(mask_overlap_offset(v, f, cams, masks, bracket=0.005) - 0.002) < 0.0002

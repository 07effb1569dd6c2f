"""Simulation assets: repair, units, mass properties against closed forms, colours baked from splats."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from reconstruction.twin import MeshParts
from simulation.asset import bake_face_colors, build_asset, load_mesh_asset, mass_properties, repair_mesh, resolve_density
from tests.conftest import require_shared


def broken_cube():
    """Unit cube with unwelded vertices (a triangle soup), one face flipped, one face missing,
    one degenerate face and one duplicate face appended."""
    box = trimesh.creation.box(extents=[1, 1, 1])
    tri = box.vertices[box.faces]
    tri[3] = tri[3][::-1]
    tri = np.concatenate([tri[:-1], tri[:1, [0, 0, 1]], tri[5:6]])
    faces = np.arange(len(tri) * 3).reshape(-1, 3)
    return tri.reshape(-1, 3), faces


def test_repair_welds_drops_fixes_and_fills_keeping_face_data():
    v, f = broken_cube()
    labels = np.arange(len(f))
    v2, f2, data, rep = repair_mesh(v, f, {"label": labels})
    assert rep.watertight and rep.faces_removed == 2 and rep.faces_added == 1
    assert rep.vertices_welded == len(v) - 8
    assert trimesh.Trimesh(v2, f2).volume == pytest.approx(1.0)
    # Surviving faces keep their own labels; the filled one takes its nearest neighbour's.
    assert len(data["label"]) == len(f2) and set(data["label"][:-1]) == set(range(11))


def test_inside_out_mesh_is_turned_outwards():
    box = trimesh.creation.box(extents=[0.1, 0.2, 0.3])
    _, f2, _, rep = repair_mesh(box.vertices, box.faces[:, ::-1])
    assert rep.inverted and trimesh.Trimesh(box.vertices, f2).volume == pytest.approx(0.006)


def test_mass_properties_match_the_closed_form_box():
    a, b, c, rho = 0.1, 0.2, 0.3, 2700.0
    box = trimesh.creation.box(extents=[a, b, c])
    box.apply_translation([1.0, 2.0, 3.0])
    mp = mass_properties(box.vertices, box.faces, rho)
    m = rho * a * b * c
    assert mp.exact and mp.mass == pytest.approx(m)
    assert mp.center_of_mass == pytest.approx([1, 2, 3])
    assert np.diag(mp.inertia) == pytest.approx(m / 12 * np.array([b * b + c * c, a * a + c * c, a * a + b * b]))


def test_open_mesh_falls_back_to_its_hull():
    box = trimesh.creation.box(extents=[1, 1, 1])
    mp = mass_properties(box.vertices, box.faces[:-2], 1000.0)
    assert not mp.exact and mp.mass == pytest.approx(1000.0)


def test_density_from_material_or_number_and_bad_values():
    assert resolve_density(None, None) == (1050.0, "plastic")
    assert resolve_density(None, "Steel") == (7850.0, "steel")
    assert resolve_density(500.0, "steel")[0] == 500.0
    with pytest.raises(ValueError, match="unknown material"):
        resolve_density(None, "unobtainium")
    with pytest.raises(ValueError, match="positive"):
        resolve_density(-1.0, None)


def test_bake_face_colors_follow_nearby_splats():
    rng = np.random.default_rng(0)
    red = rng.normal(size=(200, 3)) * 0.01 + [-0.1, 0, 0]
    blue = rng.normal(size=(200, 3)) * 0.01 + [0.1, 0, 0]
    rgb = np.concatenate([np.tile([1.0, 0, 0], (200, 1)), np.tile([0, 0, 1.0], (200, 1))])
    faces = bake_face_colors(np.array([[-0.1, 0, 0], [0.1, 0, 0]]), np.concatenate([red, blue]), rgb, np.ones(400))
    assert faces == pytest.approx(np.array([[1, 0, 0], [0, 0, 1.0]]), abs=1e-6)


def test_flat_mesh_has_no_mass():
    square = MeshParts(np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]]), np.array([[0, 1, 2], [0, 2, 3]]), np.zeros(2, int), ["p"])
    with pytest.raises(ValueError, match="no volume"):
        build_asset("flat", square)


def test_units_are_declared_or_refused():
    parts = require_shared("cad", "parts")
    with pytest.raises(ValueError, match="declare its unit"):
        load_mesh_asset(parts / "torus.STL")
    counter = load_mesh_asset(parts / "counter.unitsmm.STL")  # the name declares millimetres
    assert np.ptp(counter.vertices, 0).max() == pytest.approx(0.3048, rel=1e-4)
    assert len(counter.part_names) == 6  # six separate solids -> six parts


def test_ycb_object_keeps_its_texture_colour():
    asset = load_mesh_asset(require_shared("objects", "ycb", "011_banana", "textured.obj"), "m", "banana")
    mean = asset.face_rgb.mean(0)
    assert asset.repair.watertight and asset.mass.exact
    assert mean[0] > 0.6 and mean[1] > 0.5 and mean[2] < 0.2  # yellow
    assert asset.mass.volume == pytest.approx(asset.trimesh().volume)

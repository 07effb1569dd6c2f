"""Mesh files: one reader for the library, twins and simulation; parts from the file's nodes and
objects, welding and splitting into connected pieces only when asked; GLB round trip; declared units."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from reconstruction.mesh_io import MeshError, MeshParts, component_labels, parts_glb_bytes, read_mesh_parts, unit_of
from tests.conftest import require_shared


def box(extents, centre=(0, 0, 0)) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents).apply_translation(centre)


def test_connected_components_label_faces():
    mesh = trimesh.util.concatenate([box([1, 1, 1]), box([1, 1, 1], (3, 0, 0))])
    labels = component_labels(mesh.faces, len(mesh.vertices))
    assert list(labels) == [0] * 12 + [1] * 12


def test_parts_from_obj_objects_and_glb_nodes(tmp_path):
    obj = tmp_path / "two.obj"
    a, b = box([1, 1, 1]), box([1, 1, 1], (3, 0, 0))
    lines = ["o lid"] + [f"v {x} {y} {z}" for x, y, z in a.vertices] + [f"f {i + 1} {j + 1} {k + 1}" for i, j, k in a.faces]
    lines += ["o base"] + [f"v {x} {y} {z}" for x, y, z in b.vertices] + [f"f {i + 9} {j + 9} {k + 9}" for i, j, k in b.faces]
    obj.write_text("\n".join(lines) + "\n")
    parts = read_mesh_parts(obj)
    assert sorted(parts.part_names) == ["base", "lid"]
    lid = parts.part_names.index("lid")
    assert parts.vertices[parts.faces[parts.face_part == lid]].reshape(-1, 3)[:, 0].max() == pytest.approx(0.5)
    scene = trimesh.Scene()
    scene.add_geometry(a, node_name="deck", geom_name="deck")
    scene.add_geometry(b, node_name="wheel", geom_name="wheel")
    (tmp_path / "s.glb").write_bytes(scene.export(file_type="glb"))
    assert sorted(read_mesh_parts(tmp_path / "s.glb").part_names) == ["deck", "wheel"]
    # Parts come from the file, so asking to split leaves a file with named parts as it is.
    assert sorted(read_mesh_parts(tmp_path / "s.glb", split_components=True).part_names) == ["deck", "wheel"]


def test_one_piece_stl_is_one_part_unless_split():
    path = require_shared("cad", "parts", "counter.unitsmm.STL")
    whole = read_mesh_parts(path)
    assert whole.part_names == ["counter.unitsmm.STL"] and len(whole.vertices) == 3 * len(whole.faces)  # STL repeats vertices
    welded = read_mesh_parts(path, weld=True)
    assert len(welded.vertices) < len(whole.vertices) and np.array_equal(welded.vertices[welded.faces], whole.vertices[whole.faces])
    split = read_mesh_parts(path, split_components=True)
    assert len(split.part_names) == 6 and np.bincount(split.face_part).min() > 0
    assert split.part_names[0] == "component_0" and len(split.faces) == len(whole.faces)


def test_glb_round_trip_keeps_parts_in_the_object_frame(tmp_path):
    mesh = MeshParts(
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]), np.array([[0, 1, 2], [0, 1, 3]]), np.array([0, 1]), ["floor", "wall"]
    )
    (tmp_path / "m.glb").write_bytes(parts_glb_bytes(mesh))
    back = read_mesh_parts(tmp_path / "m.glb")
    assert sorted(back.part_names) == ["floor", "wall"]
    for p, name in enumerate(mesh.part_names):  # z up again, not glTF's y up
        tri = back.vertices[back.faces[back.face_part == back.part_names.index(name)]]
        assert tri == pytest.approx(mesh.vertices[mesh.faces[mesh.face_part == p]])


def test_textured_obj_gives_face_colours():
    parts = read_mesh_parts(require_shared("objects", "ycb", "011_banana", "textured.obj"))
    assert parts.face_rgb.shape == (len(parts.faces), 3) and parts.face_rgb.mean(0)[0] > 0.6


def test_bad_files_are_one_sentence(tmp_path):
    with pytest.raises(MeshError, match="no such mesh file"):
        read_mesh_parts(tmp_path / "missing.stl")
    (tmp_path / "garbage.obj").write_text("this is not a mesh\n")
    with pytest.raises(MeshError, match=r"garbage\.obj: (cannot be read as a mesh|holds no triangles)"):
        read_mesh_parts(tmp_path / "garbage.obj")


def test_declared_units(tmp_path):
    assert unit_of(tmp_path / "plate.unitsmm.stl", "m") == "mm"
    assert unit_of(tmp_path / "plate.stl", "in") == "in"
    (tmp_path / "units.json").write_text(json.dumps({"bar.stl": "cm", "rod.stl": "ft"}))
    assert unit_of(tmp_path / "bar.stl", "m") == "cm"
    with pytest.raises(MeshError, match="unit 'ft' for rod.stl is not one of m, mm, cm, in"):
        unit_of(tmp_path / "rod.stl", "m")

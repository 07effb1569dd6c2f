"""MJCF packages: MuJoCo loads them, and its mass, centre of mass and inertia agree with trimesh's
volume properties at the same density (1 % acceptance); files are listed with their sha256."""

from __future__ import annotations

import json

import mujoco
import numpy as np
import pytest
import trimesh

from calibration.fileio import sha256_file
from calibration.so3 import quat_to_matrix
from reconstruction.mesh_io import MeshParts
from simulation.asset import build_asset, choose_density, load_mesh_asset
from simulation.collision import DecompositionOptions, collision_geometry
from simulation.mjcf import BodySpec, face_atlas, write_mjcf_package
from simulation.run import load_model
from tests.conftest import require_shared

IDENTITY = np.array([1.0, 0, 0, 0])


def body_inertia_in_body_frame(model, b: int) -> tuple[float, np.ndarray, np.ndarray]:
    """MuJoCo's mass, centre of mass and full inertia tensor (about the COM) in the body frame."""
    r = quat_to_matrix(model.body_iquat[b])
    return float(model.body_mass[b]), model.body_ipos[b].copy(), r @ np.diag(model.body_inertia[b]) @ r.T


def assert_inertia_matches(model, b: int, asset) -> None:
    mass, com, inertia = body_inertia_in_body_frame(model, b)
    assert mass == pytest.approx(asset.mass.mass, rel=1e-2)
    size = float(np.ptp(asset.vertices, 0).max())
    assert np.abs(com - asset.mass.center_of_mass).max() < 1e-2 * size
    ref = asset.mass.inertia
    assert np.abs(inertia - ref).max() < 1e-2 * np.abs(ref).max()
    # Independent check against trimesh itself at the same density.
    tm = trimesh.Trimesh(asset.vertices, asset.faces)
    tm.density = asset.density.value
    assert mass == pytest.approx(tm.mass, rel=1e-2)
    assert np.abs(inertia - tm.moment_inertia).max() < 1e-2 * np.abs(tm.moment_inertia).max()


@pytest.mark.parametrize(
    "where, unit, material",
    [(("objects", "ycb", "072-c_toy_airplane", "textured.obj"), "m", "plastic"), (("cad", "parts", "idler_riser.STL"), "in", "steel")],
)
def test_exact_mesh_inertia_agrees_with_trimesh(where, unit, material, tmp_path):
    asset = load_mesh_asset(require_shared(*where), unit, "body", density=choose_density(material=material))
    col = collision_geometry(asset.vertices, asset.faces, asset.mass.volume, decomposition=None)
    model = load_model(write_mjcf_package(tmp_path / "pkg", [BodySpec(asset, col, np.zeros(3), IDENTITY)]))
    assert_inertia_matches(model, 1, asset)


def torus_asset():
    t = trimesh.creation.torus(major_radius=0.05, minor_radius=0.015, major_sections=32, minor_sections=16)
    rgb = np.where(t.triangles_center[:, :1] > 0, [[1.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    return build_asset(
        "torus",
        MeshParts(t.vertices, t.faces, np.zeros(len(t.faces), int), ["ring"]),
        face_rgb=rgb,
        density=choose_density(material="rubber"),
    )


def test_scene_package_with_decomposition_primitive_and_fixture(tmp_path):
    torus = torus_asset()
    col = collision_geometry(
        torus.vertices,
        torus.faces,
        torus.mass.volume,
        decomposition=DecompositionOptions(max_convex_hull=6, rounds=1, mcts_iterations=20, resolution=500, timeout_s=600),
    )
    box_mesh = trimesh.creation.box(extents=[0.3, 0.3, 0.02])
    box = build_asset(
        "plate", MeshParts(box_mesh.vertices, box_mesh.faces, np.zeros(12, int), ["plate"]), density=choose_density(material="wood")
    )
    box_col = collision_geometry(box.vertices, box.faces, box.mass.volume)
    bodies = [BodySpec(box, box_col, np.array([0, 0, 0.01]), IDENTITY, fixed=True), BodySpec(torus, col, np.array([0, 0, 0.1]), IDENTITY)]
    xml = write_mjcf_package(tmp_path / "scene", bodies)
    model = load_model(xml)
    assert [model.body(i).name for i in range(1, model.nbody)] == ["plate", "torus"]
    assert model.njnt == 1  # the fixture has no joint
    assert_inertia_matches(model, 2, torus)
    # Collision geoms carry no mass; the visual mesh does not collide.
    for g in range(model.ngeom):
        name = model.geom(g).name
        if name.endswith("_visual"):
            assert model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0
    kinds = {model.geom(g).name: int(model.geom_type[g]) for g in range(model.ngeom)}
    assert kinds["plate_collision_box_0"] == mujoco.mjtGeom.mjGEOM_BOX
    assert sum(n.startswith("torus_collision_") for n in kinds) == col.hull_count >= 2
    manifest = json.loads((tmp_path / "scene" / "manifest.json").read_text())
    assert manifest["bodies"][1]["collision"]["kind"] == "decomposition"
    for rel, digest in manifest["sha256"].items():
        assert sha256_file(tmp_path / "scene" / rel) == digest
    assert manifest["contact"]["solref"] == [0.002, 1.0]


def test_texture_atlas_holds_each_face_colour(tmp_path):
    torus = torus_asset()
    tex = face_atlas(torus.face_rgb)
    n = tex.shape[0]
    i = np.arange(len(torus.faces))
    assert np.array_equal(tex[i // n, i % n], (torus.face_rgb * 255 + 0.5).astype(np.uint8))


def test_duplicate_body_names_are_refused(tmp_path):
    t = torus_asset()
    col = collision_geometry(t.vertices, t.faces, t.mass.volume, decomposition=None)
    with pytest.raises(ValueError, match="unique"):
        write_mjcf_package(tmp_path / "x", [BodySpec(t, col, np.zeros(3), IDENTITY)] * 2)

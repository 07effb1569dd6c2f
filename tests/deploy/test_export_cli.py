"""`cadsplat export`: files that open right in the tools engineers use.

- ply: read the way Inria's 3DGS loader reads it (no --sh_degree flag: it expects degree 3).
- glb: +Y up, the part standing as on the rig; 0 errors in the Khronos glTF validator when it is
  installed (`make env` puts it in .venv/node when npm reaches its registry; CADSPLAT_GLTF_VALIDATOR
  or npm's global root also count; skipped otherwise).
- usd: pxr reads it back as a rigid body with the MJCF's mass and mesh, and collision prims.
- mjcf: density from the flag, rig.toml's [simulation] table or the default, said in the manifest;
  a mesh that cannot be closed is refused in one sentence.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
import trimesh

from benchmarks._common import gltf_validator
from deploy.cli import main
from reconstruction.mesh_io import MeshParts
from reconstruction.twin import load_twin, read_splats_ply
from simulation.run import load_model
from tests.simulation.twins import assemble, box, hammer, make_twin


@pytest.fixture(scope="module")
def twin_dir(tmp_path_factory):
    return make_twin(tmp_path_factory.mktemp("twins"), "hammer", *hammer(), n=1500)


def test_ply_reads_in_inrias_loader_without_flags(twin_dir, tmp_path):
    from plyfile import PlyData

    assert main(["export", str(twin_dir), "--format", "ply", "--out", str(tmp_path / "s.ply")]) == 0
    twin = load_twin(twin_dir)
    # As gaussian_model.load_ply does with its default max_sh_degree = 3.
    v = PlyData.read(str(tmp_path / "s.ply")).elements[0]
    extra = sorted((p.name for p in v.properties if p.name.startswith("f_rest_")), key=lambda n: int(n.split("_")[-1]))
    max_sh_degree = 3
    assert len(extra) == 3 * (max_sh_degree + 1) ** 2 - 3
    rest = np.stack([np.asarray(v[n]) for n in extra], 1).reshape(len(v["x"]), 3, (max_sh_degree + 1) ** 2 - 1)
    np.testing.assert_allclose(rest[:, :, :3], twin.gaussians.sh[:, 1:4].transpose(0, 2, 1), atol=1e-6)  # the fitted degree-1 band
    assert not rest[:, :, 3:].any()  # degrees 2 and 3: zero padding, renders identically
    np.testing.assert_allclose(np.stack([v["f_dc_0"], v["f_dc_1"], v["f_dc_2"]], 1), twin.gaussians.sh[:, 0], atol=1e-6)
    assert read_splats_ply(tmp_path / "s.ply").sh_degree == 1  # our reader drops the padding again


VALIDATE_JS = """
const fs = require('fs');
require('gltf-validator').validateBytes(new Uint8Array(fs.readFileSync(process.argv[1])))
  .then(r => console.log(JSON.stringify(r.issues)))
  .catch(e => { console.error(String(e)); process.exit(2); });
"""


def test_glb_stands_upright_in_a_y_up_viewer_and_validates(twin_dir, tmp_path):
    out = tmp_path / "hammer.glb"
    assert main(["export", str(twin_dir), "--format", "glb", "--out", str(out)]) == 0
    parts = load_twin(twin_dir).load_mesh_deformed()
    # A viewer applies the node transforms: object (x, y, z) must appear at (x, z, -y), z up -> +Y up.
    scene = trimesh.load(out, force="scene", process=False)
    viewed = np.concatenate([trimesh.transform_points(scene.geometry[g].vertices, scene.graph[n][0]) for n, g in ((n, scene.graph[n][1]) for n in scene.graph.nodes_geometry)])
    expected = parts.vertices[np.unique(parts.faces)] @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0.0]])
    assert np.allclose(np.sort(viewed, 0), np.sort(expected, 0), atol=1e-7)
    checker = gltf_validator()
    if checker is None:
        pytest.skip("the Khronos glTF validator (npm gltf-validator) is not installed")
    node, mods = checker
    res = subprocess.run([node, "-e", VALIDATE_JS, str(out)], capture_output=True, text=True, env={**os.environ, "NODE_PATH": str(mods)}, timeout=120)
    assert res.returncode == 0, res.stderr
    issues = json.loads(res.stdout)
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]


def obj_triangles(path: Path) -> np.ndarray:
    verts, tris = [], []
    for line in path.read_text().splitlines():
        if line.startswith("v "):
            verts.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("f "):
            tris.append([int(c.split("/")[0]) - 1 for c in line.split()[1:4]])
    return np.asarray(verts)[np.asarray(tris)]


def test_usd_reads_back_as_the_mjcf_body(twin_dir, tmp_path):
    from pxr import Usd, UsdGeom, UsdPhysics

    from simulation.usd import _canonical

    assert main(["export", str(twin_dir), "--format", "usd", "--out", str(tmp_path / "hammer.usda"), "--material", "steel"]) == 0
    assert main(["export", str(twin_dir), "--format", "mjcf", "--out", str(tmp_path / "mjcf"), "--material", "steel"]) == 0
    model = load_model(tmp_path / "mjcf" / "model.xml")
    stage = Usd.Stage.Open(str(tmp_path / "hammer.usda"))
    root = stage.GetDefaultPrim()
    assert root.HasAPI(UsdPhysics.RigidBodyAPI) and root.HasAPI(UsdPhysics.MassAPI)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert UsdPhysics.MassAPI(root).GetMassAttr().Get() == pytest.approx(model.body_mass[1], rel=1e-5)
    assert np.array(UsdPhysics.MassAPI(root).GetCenterOfMassAttr().Get()) == pytest.approx(model.body_ipos[1], abs=1e-6)
    assert np.sort(UsdPhysics.MassAPI(root).GetDiagonalInertiaAttr().Get()) == pytest.approx(np.sort(model.body_inertia[1]), rel=1e-4)
    visual = {p.GetName(): p for p in root.GetChild("visual").GetChildren()}
    assert sorted(visual) == ["handle", "head"]  # named as the CAD parts
    tris = []
    for prim in visual.values():
        mesh = UsdGeom.Mesh(prim)
        tris.append(np.array(mesh.GetPointsAttr().Get(), np.float64)[np.array(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)])
    mjcf_tris = obj_triangles(tmp_path / "mjcf" / "meshes" / "hammer.obj")
    assert np.allclose(_canonical(np.concatenate(tris)), _canonical(mjcf_tris), atol=1e-6)  # the same mesh, winding kept
    collision = [p for p in root.GetChild("collision").GetChildren() if p.HasAPI(UsdPhysics.CollisionAPI)]
    manifest = json.loads((tmp_path / "mjcf" / "manifest.json").read_text())["bodies"][0]
    assert len(collision) == manifest["collision"]["hulls"] + len(manifest["collision"]["primitives"]) >= 1
    for p in collision:
        if p.IsA(UsdGeom.Mesh):
            assert UsdPhysics.MeshCollisionAPI(p).GetApproximationAttr().Get() == UsdPhysics.Tokens.convexHull


def test_mjcf_density_from_rig_toml_unless_a_flag_says_otherwise(twin_dir, tmp_path):
    rig = tmp_path / "rig.toml"
    rig.write_text('rig_id = "line"\n[simulation]\nmaterial = "aluminium"\n')
    assert main(["export", str(twin_dir), "--format", "mjcf", "--out", str(tmp_path / "a"), "--rig", str(rig)]) == 0
    body = json.loads((tmp_path / "a" / "manifest.json").read_text())["bodies"][0]
    assert body["density"] == {"kg_m3": 2700.0, "material": "aluminium", "source": "rig.toml"}
    assert body["mass_kg"] == pytest.approx(2700.0 * body["volume_m3"]) and body["volume_m3"] == pytest.approx(0.14 * 0.02 * 0.016 + 0.03 * 0.07 * 0.024)
    assert len(body["principal_inertia_kg_m2"]) == 3 and body["collision"]["hausdorff_m"] > 0
    assert main(["export", str(twin_dir), "--format", "mjcf", "--out", str(tmp_path / "b"), "--rig", str(rig), "--density", "900"]) == 0
    assert json.loads((tmp_path / "b" / "manifest.json").read_text())["bodies"][0]["density"]["source"] == "flag"


def test_a_twin_that_cannot_be_closed_is_refused_in_one_sentence(tmp_path, capsys):
    sheet = trimesh.creation.box(extents=[0.1, 0.1, 0.01])
    top = sheet.faces[sheet.face_normals[:, 2] > 0.9]
    parts, rgb = assemble([("sheet", trimesh.Trimesh(sheet.vertices, top), (0.5, 0.5, 0.5))])
    twin = make_twin(tmp_path, "sheet", MeshParts(parts.vertices, parts.faces, parts.face_part, parts.part_names), rgb, n=200)
    assert main(["export", str(twin), "--format", "mjcf", "--out", str(tmp_path / "out")]) != 0
    err = capsys.readouterr().err.strip()
    assert err.startswith("Error: sheet: the mesh cannot be closed") and "\n" not in err
    assert not (tmp_path / "out" / "model.xml").exists()


def test_box_twin_collides_as_its_box(tmp_path):
    parts, rgb = assemble([("block", box([0.05, 0.03, 0.02], (0, 0, 0.01)), (0.2, 0.4, 0.8))])
    twin = make_twin(tmp_path, "block", parts, rgb, n=300)
    assert main(["export", str(twin), "--format", "mjcf", "--out", str(tmp_path / "m")]) == 0
    body = json.loads((tmp_path / "m" / "manifest.json").read_text())["bodies"][0]
    assert body["collision"]["kind"] == "box" and abs(body["collision"]["volume_error"]) < 1e-6

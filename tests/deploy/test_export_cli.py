"""`cadsplat export`: files that open right in the tools engineers use.

- ply: read the way Inria's 3DGS loader reads it (no --sh_degree flag: it expects degree 3).
- glb: the splats (and the mesh with --mesh) +Y up, the part standing as it stood on the rig, for a
  CAD model drawn Y-up and one drawn Z-up; no error in the Khronos glTF validator but the one it
  raises for not knowing KHR_gaussian_splatting yet (when it is installed: `make env` puts it in
  .venv/node when npm reaches its registry; CADSPLAT_GLTF_VALIDATOR or npm's global root also count).
- usd: pxr reads it back as a rigid body with the MJCF's mass and mesh, collision prims, and the
  twin's splats through UsdVol's schema; its upAxis is the part's up.
- spz: stands up as the glb does.
- no file export replaces an existing one without --overwrite, --out a file or a directory.
- mjcf: density from the flag, rig.toml's [simulation] table or the default, said in the manifest;
  a mesh that cannot be closed is refused in one sentence.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from calibration.sim3 import Sim3
from deploy.cli import main
from reconstruction.mesh_io import MeshParts
from reconstruction.twin import load_twin, read_splats_ply
from simulation.gltf_splats import EXTENSION, accessor_array, read_glb
from simulation.run import load_model
from tests.simulation.test_gltf_splats import errors_beyond_unknown_extension_semantics, validate
from tests.simulation.test_spz import read_spz
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


def post_twin(root: Path, drawn_up: str) -> Path:
    """A tall post (0.1 m) on a square foot, drawn in CAD with its height along `drawn_up` ("y" or "z"),
    captured standing on the conveyor: the registration takes the rig's z (up) onto the CAD's up."""
    tall = {"z": ([0.02, 0.02, 0.1], (0, 0, 0.05)), "y": ([0.02, 0.1, 0.02], (0, 0.05, 0))}[drawn_up]
    foot = {"z": ([0.05, 0.05, 0.005], (0, 0, 0.0025)), "y": ([0.05, 0.005, 0.05], (0, 0.0025, 0))}[drawn_up]
    parts, rgb = assemble([("post", box(*tall), (0.8, 0.3, 0.1)), ("foot", box(*foot), (0.2, 0.2, 0.2))])
    rig_to_object = np.eye(3) if drawn_up == "z" else np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # rig z -> CAD y
    return make_twin(root, f"post_{drawn_up}", parts, rgb, n=800, sim3_rig_to_object=Sim3(1.0, rig_to_object, np.zeros(3)))


@pytest.fixture(scope="module")
def rig_toml(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("rig") / "rig.toml"
    path.write_text('rig_id = "line"\n[simulation]\nup = [0, 0, 1]\n')
    return path


def tallest_axis(points: np.ndarray) -> int:
    return int(np.argmax(np.ptp(points, 0)))


@pytest.mark.parametrize("drawn_up", ["y", "z"])
def test_glb_and_spz_stand_the_part_up_whichever_way_its_cad_was_drawn(drawn_up, tmp_path, rig_toml):
    twin = post_twin(tmp_path, drawn_up)
    assert main(["export", str(twin), "--format", "glb", "--out", str(tmp_path / "p.glb"), "--rig", str(rig_toml), "--mesh"]) == 0
    doc, blob = read_glb((tmp_path / "p.glb").read_bytes())
    splat_prim = doc["meshes"][0]["primitives"][0]
    assert EXTENSION in splat_prim["extensions"]
    means = accessor_array(doc, blob, splat_prim["attributes"]["POSITION"])
    assert tallest_axis(means) == 1 and means[:, 1].mean() > 0.02  # standing along +Y, the foot at the bottom
    mesh_points = np.concatenate([accessor_array(doc, blob, m["primitives"][0]["attributes"]["POSITION"]) for m in doc["meshes"][1:]])
    assert tallest_axis(mesh_points) == 1 and mesh_points[:, 1].min() == pytest.approx(0.0, abs=1e-7)
    cadsplat = doc["nodes"][0]["extras"]["cadsplat"]
    assert cadsplat["up"]["source"] == "rig.toml" and len(means) == cadsplat["num_splats"] == 800
    assert cadsplat["eps2d"] == load_twin(twin).gaussians.eps2d  # the dilation a viewer draws them with
    issues = validate(tmp_path / "p.glb")
    assert errors_beyond_unknown_extension_semantics(issues) == [] and issues["numWarnings"] == 0, issues["messages"]

    assert main(["export", str(twin), "--format", "spz", "--out", str(tmp_path / "p.spz"), "--cad-up-axis", drawn_up]) == 0
    spz = read_spz((tmp_path / "p.spz").read_bytes())
    assert tallest_axis(spz["means"]) == 1 and spz["means"][:, 1].mean() > 0.02  # the CAD's declared axis, up in spz's RUB frame


def test_without_any_up_the_default_is_said_and_a_y_up_cad_lies_on_its_side(tmp_path):
    twin = post_twin(tmp_path, "y")
    assert main(["export", str(twin), "--format", "glb", "--out", str(tmp_path / "p.glb")]) == 0
    doc, blob = read_glb((tmp_path / "p.glb").read_bytes())
    assert doc["nodes"][0]["extras"]["cadsplat"]["up"]["source"] == "default"
    assert tallest_axis(accessor_array(doc, blob, doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"])) == 2


def obj_triangles(path: Path) -> np.ndarray:
    verts, tris = [], []
    for line in path.read_text().splitlines():
        if line.startswith("v "):
            verts.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("f "):
            tris.append([int(c.split("/")[0]) - 1 for c in line.split()[1:4]])
    return np.asarray(verts)[np.asarray(tris)]


def test_usd_reads_back_as_the_mjcf_body_with_the_twins_splats(twin_dir, tmp_path):
    from pxr import Usd, UsdGeom, UsdPhysics, UsdVol

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
    twin = load_twin(twin_dir)
    field = UsdVol.ParticleField3DGaussianSplat(root.GetChild("splats"))
    assert field and len(field.GetPositionsAttr().Get()) == twin.num_splats == len(field.GetOpacitiesAttr().Get())
    assert field.GetRadianceSphericalHarmonicsDegreeAttr().Get() == twin.gaussians.sh_degree == 1
    sh = np.array(field.GetRadianceSphericalHarmonicsCoefficientsAttr().Get()).reshape(twin.num_splats, 4, 3)
    np.testing.assert_allclose(sh, twin.gaussians.sh, atol=1e-7)  # as fitted: 3DGS's basis and order, DC first
    np.testing.assert_allclose(np.array(field.GetScalesAttr().Get()), np.exp(twin.gaussians.log_scales), rtol=1e-6)
    assert stage.GetRootLayer().customLayerData["cadsplat:up_source"] == "default"


def test_usd_of_a_y_up_cad_is_a_y_up_stage_in_the_object_frame_and_mujoco_stands_it_on_z(tmp_path, rig_toml):
    from pxr import Usd, UsdGeom, UsdVol

    from calibration.so3 import quat_to_matrix

    twin = post_twin(tmp_path, "y")
    assert main(["export", str(twin), "--format", "mjcf", "--out", str(tmp_path / "m"), "--rig", str(rig_toml), "--hull-budget", "8"]) == 0
    manifest = json.loads((tmp_path / "m" / "manifest.json").read_text())
    body = manifest["bodies"][0]
    assert manifest["up"]["source"] == "rig.toml" and body["collision"]["hulls"] <= body["collision"]["hull_budget"] == 8
    assert quat_to_matrix(np.array(body["pose"]["quat_wxyz"])) @ [0, 1, 0] == pytest.approx([0, 0, 1])  # object +y onto MuJoCo's +z
    model = load_model(tmp_path / "m" / "model.xml")
    assert model.body_pos[1][2] == pytest.approx(0.0, abs=1e-6)  # the foot (object y = 0) on the floor
    assert main(["export", str(twin), "--format", "usd", "--out", str(tmp_path / "p.usda"), "--rig", str(rig_toml)]) == 0
    stage = Usd.Stage.Open(str(tmp_path / "p.usda"))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert np.array(stage.GetRootLayer().customLayerData["cadsplat:stage_from_object"]) == pytest.approx(np.eye(4).reshape(-1))
    means = np.array(UsdVol.ParticleField3DGaussianSplat(stage.GetDefaultPrim().GetChild("splats")).GetPositionsAttr().Get())
    np.testing.assert_allclose(means, load_twin(twin).gaussians.means, atol=1e-7)


@pytest.mark.parametrize("fmt,name", [("ply", "splats.ply"), ("glb", "splats.glb"), ("spz", "splats.spz"), ("usd", "hammer.usda")])
def test_no_file_export_replaces_an_existing_one_without_overwrite(fmt, name, twin_dir, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / name).write_bytes(b"keep me")
    assert main(["export", str(twin_dir), "--format", fmt, "--out", str(out)]) != 0  # --out a directory
    assert "already exists; pass --overwrite" in capsys.readouterr().err and (out / name).read_bytes() == b"keep me"
    assert main(["export", str(twin_dir), "--format", fmt, "--out", str(out / name)]) != 0  # --out the file
    assert (out / name).read_bytes() == b"keep me"
    if fmt != "usd":  # the USD export decomposes the body; the replacing itself is the same code
        assert main(["export", str(twin_dir), "--format", fmt, "--out", str(out), "--overwrite"]) == 0
        assert (out / name).read_bytes() != b"keep me"


def test_mjcf_density_from_rig_toml_unless_a_flag_says_otherwise(twin_dir, tmp_path):
    rig = tmp_path / "rig.toml"
    rig.write_text('rig_id = "line"\n[simulation]\nmaterial = "aluminium"\n')
    assert main(["export", str(twin_dir), "--format", "mjcf", "--out", str(tmp_path / "a"), "--rig", str(rig)]) == 0
    body = json.loads((tmp_path / "a" / "manifest.json").read_text())["bodies"][0]
    assert body["density"] == {"kg_m3": 2700.0, "material": "aluminium", "source": "rig.toml"}
    assert body["mass_kg"] == pytest.approx(2700.0 * body["volume_m3"]) and body["volume_m3"] == pytest.approx(
        0.14 * 0.02 * 0.016 + 0.03 * 0.07 * 0.024
    )
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

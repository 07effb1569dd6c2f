"""The USD asset stood on an up that is neither of USD's axes: the whole body turns together and the
file says how; read back through pxr with the schema's API before it is renamed into place."""

from __future__ import annotations

import numpy as np
import pytest

from reconstruction.twin import load_twin
from simulation.export import twin_body
from simulation.up import Up
from simulation.usd import UsdCheckError, check_usd, turned_body, write_usd
from tests.simulation.twins import make_twin, skateboard


@pytest.fixture(scope="module")
def skateboard_twin(tmp_path_factory):
    return make_twin(tmp_path_factory.mktemp("twins"), "skateboard", *skateboard(), n=600)


def test_a_tilted_up_turns_mesh_splats_mass_and_collision_together(skateboard_twin, tmp_path):
    from pxr import Usd, UsdGeom, UsdPhysics, UsdVol

    twin = load_twin(skateboard_twin)
    body = twin_body(skateboard_twin, twin=twin)
    up = Up(np.array([0.3, -0.2, 0.93]) / np.linalg.norm([0.3, -0.2, 0.93]), "cad", "test")
    path = write_usd(tmp_path / "board.usdc", body, twin.gaussians, up)
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    r = np.array(stage.GetRootLayer().customLayerData["cadsplat:stage_from_object"]).reshape(4, 4)[:3, :3]
    assert r @ up.vector == pytest.approx([0, 0, 1]) and stage.GetRootLayer().customLayerData["cadsplat:up_source"] == "cad"
    root = stage.GetDefaultPrim()
    mass = UsdPhysics.MassAPI(root)
    assert mass.GetMassAttr().Get() == pytest.approx(body.asset.mass.mass, rel=1e-6)
    assert np.array(mass.GetCenterOfMassAttr().Get()) == pytest.approx(r @ body.asset.mass.center_of_mass, abs=1e-6)
    means = np.array(UsdVol.ParticleField3DGaussianSplat(root.GetChild("splats")).GetPositionsAttr().Get())
    assert means == pytest.approx(np.asarray(twin.gaussians.means) @ r.T, abs=1e-6)
    turned = turned_body(body, r)
    assert turned.collision.primitives[0].transform[:3, :3] == pytest.approx(r @ body.collision.primitives[0].transform[:3, :3])
    assert np.sort(np.linalg.eigvalsh(turned.asset.mass.inertia)) == pytest.approx(np.sort(body.asset.mass.principal_moments))


def test_a_file_that_does_not_hold_the_splats_is_caught(skateboard_twin, tmp_path):
    twin = load_twin(skateboard_twin)
    body = twin_body(skateboard_twin, twin=twin)
    path = write_usd(tmp_path / "board.usda", body, twin.gaussians)
    fewer = twin.gaussians.subset(np.arange(len(twin.gaussians) - 1))
    with pytest.raises(UsdCheckError, match="599 splats"):
        check_usd(path, body, fewer)

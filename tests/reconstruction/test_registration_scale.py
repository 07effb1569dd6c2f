"""Registration scale: a metric rig measures the part (a wrong-size look-alike loses, the deviation is
reported), an unknown-scale rig registers at any scale and reports the look-alike as a tie."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from calibration.sim3 import Sim3
from calibration.so3 import geodesic_angle_deg
from reconstruction.library import build_library
from reconstruction.registration import SCALE_SEARCH, RegistrationError, register, scale_band
from tests.reconstruction.test_registration import GRID, bracket, ring, scene, true_sim3


@pytest.fixture(scope="module")
def lookalike_lib(tmp_path_factory):
    """The true part and a copy 1.5 times its size (same shape, same frame origin scaled)."""
    d = tmp_path_factory.mktemp("meshes")
    bracket().export(d / "bracket.stl")
    big = bracket()
    big.apply_scale(1.5)
    big.export(d / "bracket_x1.5.stl")
    trimesh.creation.cylinder(0.02, 0.15, sections=32).export(d / "rod.stl")
    return build_library(d, tmp_path_factory.mktemp("lib"), grid=GRID, workers=1, progress=False, log=lambda s: None)


def metric_scene(part_scale: float, seed: int):
    """A metric rig (metres, cameras 0.5 m out) looking at the bracket made `part_scale` times its CAD size."""
    mesh = bracket()
    c = mesh.bounds.mean(0)
    physical = mesh.copy()
    physical.apply_translation(-c)
    physical.apply_scale(part_scale)
    physical.apply_translation(c)
    gt = true_sim3(mesh, 1.0, seed=seed)
    masks, cams = scene(physical, ring(9, 0.5), gt)
    return masks, cams, gt


def test_scale_band():
    assert scale_band(None) == SCALE_SEARCH and SCALE_SEARCH[0] <= 0.1 and SCALE_SEARCH[1] >= 10
    lo, hi = scale_band(1.0, 0.1)
    # A part up to 10 % larger (s = 1/1.1) or smaller (s = 1/0.9) than its CAD model.
    assert lo == pytest.approx(1 / 1.1) and hi == pytest.approx(1 / 0.9)
    assert scale_band(1e-3, 0.1)[0] == pytest.approx(1e-3 / 1.1)
    with pytest.raises(RegistrationError, match="tolerance"):
        scale_band(1.0, 1.5)


def test_metric_rig_picks_the_true_size_and_measures_the_deviation(lookalike_lib):
    masks, cams, gt = metric_scene(1.032, seed=3)
    res = register(masks, cams, lookalike_lib, rig_metres_per_unit=1.0)
    assert res.model_id == "bracket"
    assert res.model_ties == []
    assert res.part_scale_vs_cad == pytest.approx(1.032, abs=0.012)
    assert "larger than its CAD model" in res.scale_statement()
    d = res.to_dict()["scale"]
    assert d["metric"] and d["band"][0] < 1.0 < d["band"][1]
    assert geodesic_angle_deg(res.sim3_rig_to_object.rotation, gt.rotation) < 3.0


def test_metric_rig_refuses_a_part_outside_the_tolerance(lookalike_lib):
    # A part 1.5 times its CAD size on a metric rig fits the big copy, never the small one stretched.
    masks, cams, _ = metric_scene(1.5, seed=5)
    res = register(masks, cams, lookalike_lib, rig_metres_per_unit=1.0)
    assert res.model_id == "bracket_x1.5"
    assert res.part_scale_vs_cad == pytest.approx(1.0, abs=0.02)


@pytest.mark.parametrize("k", [0.2, 5.0])
def test_unknown_scale_registers_and_reports_the_lookalike_tie(lookalike_lib, k):
    # The same metric scene with its rig frame scaled by k and no units: the scale is searched.
    masks, cams, gt = metric_scene(1.0, seed=3)
    cams_k = []
    for c in cams:
        c2w = c.c2w.copy()
        c2w[:3, 3] *= k
        cams_k.append(c.with_c2w(c2w))
    res = register(masks, cams_k, lookalike_lib)
    assert res.model_id in ("bracket", "bracket_x1.5")
    other = "bracket_x1.5" if res.model_id == "bracket" else "bracket"
    ties = {t["model_id"]: t for t in res.model_ties}
    ratio = 1.5 if other == "bracket_x1.5" else 1 / 1.5
    assert other in ties and ties[other]["cad_size_ratio"] == pytest.approx(ratio, rel=0.01)
    assert ties[other]["scale_ratio"] == pytest.approx(ratio, rel=0.03) and ties[other]["score_gap"] < 0.03
    assert res.part_scale_vs_cad is None and res.scale_statement() is None
    # The big copy's frame is the small one's times 1.5: the true Sim(3) for either model at rig scale k.
    f = 1.5 if res.model_id == "bracket_x1.5" else 1.0
    true = Sim3(f * gt.scale / k, gt.rotation, f * gt.translation)
    assert res.sim3_rig_to_object.scale == pytest.approx(true.scale, rel=0.04)
    assert geodesic_angle_deg(res.sim3_rig_to_object.rotation, true.rotation) < 3.0
    centres = np.array([c.center for c in cams_k])
    err = np.linalg.norm(res.sim3_rig_to_object.apply(centres) - true.apply(centres), axis=1)
    assert np.median(err / np.linalg.norm(true.apply(centres) - true.translation, axis=1)) < 0.05

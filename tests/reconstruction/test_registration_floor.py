"""A registration is never confidently wrong (issue 60): a flat disc at unknown scale registers, and a fit below the
silhouette floor is refused in one sentence naming the views where the part lies outside its mask."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from reconstruction.library import build_library
from reconstruction.quality import MaskGate, QualityError, check_registration
from reconstruction.registration import register
from tests.reconstruction.test_registration import GRID, bracket, ring, scene, true_sim3


def disc() -> trimesh.Trimesh:
    """A lid: 10 cm across, 6 mm thick."""
    return trimesh.creation.cylinder(0.05, 0.006, sections=48)


@pytest.fixture(scope="module")
def disc_lib(tmp_path_factory):
    d = tmp_path_factory.mktemp("meshes")
    disc().export(d / "disc.stl")
    bracket().export(d / "bracket.stl")
    trimesh.creation.cylinder(0.02, 0.15, sections=32).export(d / "rod.stl")
    return build_library(d, tmp_path_factory.mktemp("lib"), grid=GRID, workers=1, progress=False, log=lambda s: None)


@pytest.mark.parametrize("k", [3.3, 0.3])
def test_a_flat_disc_registers_at_unknown_scale(disc_lib, k):
    mesh = disc()
    gt = true_sim3(mesh, 0.35 * k, seed=3)
    masks, cams = scene(mesh, ring(9), gt)
    res = register(masks, cams, disc_lib)
    assert res.model_id == "disc" and res.per_view_iou.min() > 0.9
    assert res.sim3_rig_to_object.scale == pytest.approx(gt.scale, rel=0.02)
    # A disc turns freely about its axis and flips over: only its axis is determined.
    axis = np.array([0.0, 0.0, 1.0])
    assert abs(abs((res.sim3_rig_to_object.rotation.T @ axis) @ (gt.rotation.T @ axis)) - 1.0) < 1e-2
    check_registration(res.score, res.alternatives, masks, 3, res.model_id, per_view_iou=res.per_view_iou)


def test_a_fit_below_the_floor_is_refused_naming_the_views(disc_lib):
    mesh = disc()
    masks, cams = scene(mesh, ring(9), true_sim3(mesh, 0.35, seed=3))
    # The wrong part forced on the disc's silhouettes: the rod cannot cover them.
    res = register(masks, cams, disc_lib, model_ids=["rod"], iou_threshold=0.0)
    assert res.score < MaskGate().fit_floor
    names = [f"view {i} (cam{i:02d})" for i in range(9)]
    with pytest.raises(QualityError) as e:
        check_registration(res.score, res.alternatives, masks, 3, res.model_id, per_view_iou=res.per_view_iou, names=names)
    msg = str(e.value)
    below = [names[i] for i in np.flatnonzero(res.per_view_iou < MaskGate().fit_floor)]
    assert msg.startswith("registration refused: 'rod' fits these silhouettes with mean IoU") and "below the floor 0.50" in msg
    assert f"outside its mask in {len(below)} of 9 views ({', '.join(below)})" in msg and "\n" not in msg

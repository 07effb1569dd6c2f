"""The engine's edge: a metric rig fixes the registration's scale about the object's centre."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix
from reconstruction.pipeline import metric_sim3


def test_metric_rig_fixes_the_scale_and_keeps_the_object_in_place():
    reg = Sim3(1.06, axis_angle_to_matrix(np.array([0.2, -0.1, 0.4])), np.array([0.01, 0.2, -0.3]))
    centre = np.array([0.02, -0.01, 0.03])
    snapped = metric_sim3(reg, 1e-3, centre)  # a rig calibrated in millimetres, CAD in metres
    assert snapped.scale == 1e-3
    np.testing.assert_allclose(snapped.rotation, reg.rotation)
    # The object's centre sits where the registration put it in the rig.
    np.testing.assert_allclose(snapped.inverse().apply(centre[None]), reg.inverse().apply(centre[None]), atol=1e-12)


@pytest.mark.slow
def test_a_capture_whose_calibration_measured_up_stands_a_y_up_cad_upright(tmp_path, monkeypatch):
    """The calibration's up (its board lying on the conveyor: rig +z on the sample's rig) travels in the capture to
    the twin, which records it in the object frame; the GLB then stands a CAD model drawn Y-up along +Y and says so."""
    import json
    import shutil
    from dataclasses import replace

    import trimesh

    from deploy.commands.demo import bundled_sample_dir
    from reconstruction import presets
    from reconstruction.library import build_library
    from reconstruction.pipeline import reconstruct_capture
    from reconstruction.twin import load_twin
    from simulation.export import export_glb
    from simulation.gltf_splats import read_glb

    sample = bundled_sample_dir()
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    clamp = trimesh.load(sample / "library_meshes" / "medium_clamp_cad.ply", process=False)
    clamp.vertices = clamp.vertices @ np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # drawn Y-up: its z turned onto y
    clamp.export(meshes / "medium_clamp_cad.ply")
    build_library(meshes, tmp_path / "library", progress=False, log=lambda _m: None)
    capture = tmp_path / "capture"
    shutil.copytree(sample / "train", capture)
    doc = json.loads((capture / "transforms.json").read_text())
    up = {"vector": [0.0, 0.0, 1.0], "source": "calibration", "detail": "board frame 'conveyor' lying face up on the conveyor"}
    doc["cadsplat"]["up_rig"] = up
    (capture / "transforms.json").write_text(json.dumps(doc))
    original = presets.resolve_preset
    monkeypatch.setattr(
        "reconstruction.presets.resolve_preset",
        lambda name, stats: replace(original(name, stats), iters_pose=10, iters_deform=5, iters_photo=10, dropout_anneal=5),
    )
    reconstruct_capture(capture, tmp_path / "library", tmp_path / "twin", preset="preview", views=[0, 2, 4, 6, 8])

    twin = load_twin(tmp_path / "twin")
    assert twin.up_object["source"] == "calibration" and "conveyor" in twin.up_object["detail"]
    assert np.degrees(np.arccos(np.clip(twin.up_object["vector"][1], -1, 1))) < 5.0  # the CAD's +y, as it was drawn
    glb, _ = read_glb(export_glb(tmp_path / "twin", tmp_path / "twin.glb").read_bytes())
    extras = glb["nodes"][0]["extras"]["cadsplat"]
    assert extras["up"]["source"] == "calibration" and "recorded in twin.json" in extras["up"]["detail"]
    gltf_from_object = np.asarray(extras["gltf_from_object"])[:3, :3]
    assert gltf_from_object @ np.asarray(twin.up_object["vector"]) == pytest.approx([0, 1, 0], abs=1e-9)
    assert np.degrees(np.arccos(gltf_from_object[1, 1])) < 5.0  # the CAD's +y stays glTF's +Y: the part stands as drawn

"""`cadsplat evaluate`: metrics.json with every metric per view and averaged, timings; bad input is one sentence."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
import trimesh

from calibration.capture import FrameData, write_capture
from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix
from deploy.cli import main
from reconstruction.evaluation import METRIC_KEYS
from reconstruction.mesh_io import MeshParts
from reconstruction.symmetry import rotation_about
from reconstruction.twin import save_twin
from tests.reconstruction.test_evaluation import make_twin, orbit_camera, photograph, shifted

RIG_TO_OBJECT = Sim3(2.0, axis_angle_to_matrix(np.array([0.0, 0.0, 0.7])), np.array([0.01, -0.02, 0.0]))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A saved twin registered to a rig frame and a 3-view held-out capture of it (one view mis-calibrated)."""
    root = tmp_path_factory.mktemp("eval")
    twin = make_twin(n=1200)
    twin.sim3_rig_to_object = RIG_TO_OBJECT
    save_twin(twin, root / "twin")
    g = twin.gaussians
    frames = []
    for i, az in enumerate((10.0, 130.0, 250.0)):
        cam = orbit_camera(az)
        img, mask = photograph(g, cam)
        recorded = shifted(cam, 2.0, 0.0) if i == 1 else cam
        rig_cam = recorded.with_c2w(RIG_TO_OBJECT.inverse().apply_to_c2w(recorded.c2w))
        frames.append(FrameData(f"orbit{i:02d}", img, rig_cam, f"orbit{i:02d}", mask=mask))
    write_capture(root / "heldout", frames)
    gt = {"train_c2w_object": [twin.cameras[0].c2w_object_opencv.tolist()]}
    (root / "gt.json").write_text(json.dumps(gt))
    return root


def _digest(path):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(path.iterdir()) if p.is_file()}


def test_evaluate_writes_metrics_per_view_and_averaged(scene, capsys):
    before = _digest(scene / "twin")
    out = scene / "metrics.json"
    rc = main(
        [
            "evaluate",
            str(scene / "twin"),
            "--views",
            str(scene / "heldout"),
            "--out",
            str(out),
            "--refine-steps",
            "8",
            "--gt",
            str(scene / "gt.json"),
        ]
    )
    assert rc == 0
    doc = json.loads(out.read_text())
    assert doc["num_views"] == 3 and doc["refine_steps"] == 8 and doc["num_splats"] == 1200
    assert [v["name"] for v in doc["views"]] == ["orbit00", "orbit01", "orbit02"]
    for v in doc["views"]:
        assert set(v["metrics"]) == set(METRIC_KEYS) and set(v["metrics_refined"]) == set(METRIC_KEYS)
        assert v["refine"]["steps"] == 8 and v["timings_s"]["refine"] > 0
    assert set(doc["mean"]) == set(METRIC_KEYS) and set(doc["mean_refined"]) == set(METRIC_KEYS)
    # Correctly calibrated views render exactly where their photographs are; the shifted one does not.
    ious = [v["metrics"]["iou"] for v in doc["views"]]
    assert ious[0] > 0.97 and ious[2] > 0.97 and ious[1] < 0.9
    assert doc["views"][1]["metrics_refined"]["iou"] > ious[1]
    assert doc["registration"]["rotation_deg_median"] == pytest.approx(0.0, abs=1e-6)
    for key in ("render", "refine", "metrics", "total", "load", "per_view_render_ms"):
        assert doc["timings_s"][key] >= 0
    printed = capsys.readouterr().out
    assert "3 held-out views" in printed and "refined" in printed and "registration" in printed
    assert _digest(scene / "twin") == before  # the twin on disk is untouched


def test_evaluate_max_views_without_refinement(scene, tmp_path):
    out = tmp_path / "m.json"
    assert (
        main(
            [
                "evaluate",
                str(scene / "twin"),
                "--views",
                str(scene / "heldout"),
                "--out",
                str(out),
                "--refine-steps",
                "0",
                "--max-views",
                "2",
            ]
        )
        == 0
    )
    doc = json.loads(out.read_text())
    assert [v["name"] for v in doc["views"]] == ["orbit00", "orbit02"]
    assert "mean_refined" not in doc and "metrics_refined" not in doc["views"][0]


@pytest.mark.parametrize(
    "case, fragment",
    [
        ("no_twin", "twin.json"),
        ("no_views", "transforms.json"),
        ("bad_gt", "--gt"),
        ("out_is_dir", "is a directory"),
        ("symmetry_without_gt", "need --gt"),
        ("near_symmetries_without_cad", "mesh_cad.glb"),
    ],
)
def test_evaluate_bad_input_is_one_sentence(scene, tmp_path, capsys, case, fragment):
    twin, views, out = scene / "twin", scene / "heldout", tmp_path / "m.json"
    extra: list[str] = []
    if case == "no_twin":
        twin = tmp_path / "nothing"
    elif case == "no_views":
        views = tmp_path / "nothing"
    elif case == "bad_gt":
        (tmp_path / "gt.json").write_text("{not json")
        extra = ["--gt", str(tmp_path / "gt.json")]
    elif case == "symmetry_without_gt":
        extra = ["--symmetry", "z"]
    elif case == "near_symmetries_without_cad":
        extra = ["--gt", str(scene / "gt.json"), "--near-symmetries", "2"]
    else:
        out = tmp_path
    rc = main(["evaluate", str(twin), "--views", str(views), "--out", str(out), "--refine-steps", "0", *extra])
    err = capsys.readouterr().err.strip()
    assert rc != 0
    assert fragment in err and len(err.splitlines()) == 1
    assert not (tmp_path / "m.json").exists()


def test_evaluate_forgives_a_turn_the_cad_model_cannot_show(scene, tmp_path, capsys):
    """A twin of a box registered turned 180 deg about the box's own centre: the training camera is
    180 deg off, and 0 deg off modulo the near-symmetries found on the twin's CAD mesh."""
    box = trimesh.creation.box(extents=[0.04, 0.08, 0.12])
    box.apply_translation([0.02, 0.0, 0.0])
    cad = MeshParts(np.asarray(box.vertices), np.asarray(box.faces), np.zeros(len(box.faces), np.int64), ["box"])
    twin = make_twin(n=1200)
    save_twin(twin, tmp_path / "twin", mesh_cad=cad)
    turn = rotation_about(np.array([0.0, 0.0, 1.0]), np.pi, np.array([0.02, 0.0, 0.0]))
    truth = turn @ twin.cameras[0].c2w_object_opencv  # the camera sees the object turned by `turn`
    (tmp_path / "gt.json").write_text(json.dumps({"train_c2w_object": [truth.tolist()]}))
    args = [
        "evaluate",
        str(tmp_path / "twin"),
        "--views",
        str(scene / "heldout"),
        "--refine-steps",
        "0",
        "--max-views",
        "1",
        "--gt",
        str(tmp_path / "gt.json"),
    ]
    assert main([*args, "--out", str(tmp_path / "raw.json")]) == 0
    assert json.loads((tmp_path / "raw.json").read_text())["registration"]["rotation_deg_median"] == pytest.approx(180.0)
    assert main([*args, "--out", str(tmp_path / "sym.json"), "--near-symmetries", "3"]) == 0
    reg = json.loads((tmp_path / "sym.json").read_text())["registration"]
    assert reg["rotation_deg_median"] < 0.5 and reg["symmetry"] is not None
    assert "near-symmetry moving the mesh" in capsys.readouterr().out

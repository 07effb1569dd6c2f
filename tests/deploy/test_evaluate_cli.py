"""`cadsplat evaluate`: metrics.json with every metric per view and averaged, timings; bad input is one sentence."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from calibration.capture import FrameData, write_capture
from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix
from deploy.cli import main
from reconstruction.evaluation import METRIC_KEYS, FrozenGaussians
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
    g = FrozenGaussians.from_twin(twin)
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
    rc = main(["evaluate", str(scene / "twin"), "--views", str(scene / "heldout"), "--out", str(out),
               "--refine-steps", "8", "--gt", str(scene / "gt.json")])
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
    assert main(["evaluate", str(scene / "twin"), "--views", str(scene / "heldout"), "--out", str(out),
                 "--refine-steps", "0", "--max-views", "2"]) == 0
    doc = json.loads(out.read_text())
    assert [v["name"] for v in doc["views"]] == ["orbit00", "orbit02"]
    assert "mean_refined" not in doc and "metrics_refined" not in doc["views"][0]


@pytest.mark.parametrize("case, fragment", [
    ("no_twin", "twin.json"),
    ("no_views", "transforms.json"),
    ("bad_gt", "--gt"),
    ("out_is_dir", "is a directory"),
    ("symmetry_without_gt", "--symmetry needs --gt"),
])
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
    else:
        out = tmp_path
    rc = main(["evaluate", str(twin), "--views", str(views), "--out", str(out), "--refine-steps", "0", *extra])
    err = capsys.readouterr().err.strip()
    assert rc != 0
    assert fragment in err and len(err.splitlines()) == 1
    assert not (tmp_path / "m.json").exists()

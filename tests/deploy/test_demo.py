"""`cadsplat demo` and `validate_sample`: the bundled sample is complete and consistent; damage is caught in one sentence."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from calibration.fileio import encode_png, sha256_bytes
from deploy.cli import main
from deploy.commands.demo import SampleError, bundled_sample_dir, validate_sample


@pytest.fixture()
def sample_copy(tmp_path):
    dst = tmp_path / "sample"
    shutil.copytree(bundled_sample_dir(), dst)
    return dst


def test_bundled_sample_is_small_and_valid():
    root = bundled_sample_dir()
    size = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    assert size <= 10e6, size
    info = validate_sample(root)
    assert (info["views"], info["heldout"], info["size"]) == (9, 36, [320, 240])
    assert info["mask_hit_min"] == 1.0
    true = [m for m in info["models"] if m["is_true_object"]]
    assert [m["id"] for m in true] == [info["true_model_id"]] and len(info["models"]) >= 4
    assert all(0.01 < m["extent_m"] < 0.5 for m in info["models"])  # parts in metres, not mm or inches
    assert "CC BY 4.0" in (root / "README.md").read_text()


def test_demo_prints_what_it_checked(capsys):
    assert main(["demo", "--validate-only"]) == 0
    out = capsys.readouterr().out
    assert "9 train views + 36 held-out views at 320x240" in out
    assert "100.00% of vertices inside every mask" in out and "Sample valid" in out


def test_tampered_image_is_one_sentence(sample_copy, capsys):
    img = sample_copy / "train" / "images" / "cam03.png"
    data = bytearray(img.read_bytes())
    data[100] ^= 0xFF
    img.write_bytes(bytes(data))
    assert main(["demo", "--sample", str(sample_copy)]) != 0
    err = capsys.readouterr().err
    assert "cam03.png" in err and "sha256" in err and err.count("\n") == 1


def test_wrong_ground_truth_is_caught(sample_copy):
    gt_path = sample_copy / "gt.json"
    gt = json.loads(gt_path.read_text())
    gt["sim3_rig_to_object"]["translation"][0] += 0.01
    gt_path.write_text(json.dumps(gt))
    with pytest.raises(SampleError, match="does not map the recorded poses"):
        validate_sample(sample_copy)


def test_mask_that_misses_the_object_is_caught(sample_copy):
    """A mask eroded away from the true silhouette (with its digest updated) fails the projection check."""
    tf = sample_copy / "heldout" / "transforms.json"
    doc = json.loads(tf.read_text())
    rel = doc["frames"][5]["mask_path"]
    mask = np.zeros((240, 320), np.uint8)
    mask[100:140, 140:180] = 255
    data = encode_png(mask)
    (sample_copy / "heldout" / rel).write_bytes(data)
    doc["cadsplat"]["sha256"][rel] = sha256_bytes(data)
    tf.write_text(json.dumps(doc))
    with pytest.raises(SampleError, match="vertices land inside"):
        validate_sample(sample_copy)


def test_missing_sample_dir_is_one_sentence(tmp_path, capsys):
    assert main(["demo", "--sample", str(tmp_path / "nope")]) != 0
    assert "does not exist" in capsys.readouterr().err


def test_demo_runs_the_shared_protocol_and_prints_its_record(tmp_path, monkeypatch, capsys):
    """`cadsplat demo` = library + `run_protocol` (12 held-out views, no refinement, the sample's truth);
    its figures are the record's. The protocol itself is tested in tests/reconstruction/test_evaluation.py."""
    from types import SimpleNamespace

    from reconstruction.evaluation import ProtocolResult

    calls = []

    def protocol(capture, heldout, library, out_dir, **kw):
        calls.append((capture, heldout, library, out_dir, kw))
        twin = SimpleNamespace(model_id="medium_clamp_cad", num_splats=1234)
        reg = {"rotation_deg_median": 1.25, "center_pct_median": 2.5}
        return ProtocolResult(
            twin=twin,
            registration=None,
            heldout_views=list(range(12)),
            report={"mean": {"fgpsnr": 28.33, "iou": 0.984, "psnr": 28.31}},
            reg_init=reg,
            reg_refined={"rotation_deg_median": 0.99, "center_pct_median": 1.11},
            reg_raw=None,
            timings_s={"reconstruct": 60.0, "evaluate": 5.0},
        )

    monkeypatch.setattr("reconstruction.evaluation.run_protocol", protocol)
    monkeypatch.setattr("reconstruction.library.build_library", lambda *a, **k: None)
    monkeypatch.setattr("reconstruction.render.anchor.anchor_ms", lambda: 2000.0)
    assert main(["demo", "--work", str(tmp_path / "work")]) == 0
    out = capsys.readouterr().out
    ((capture, heldout, library, twin_dir, kw),) = calls
    root = bundled_sample_dir()
    work = tmp_path / "work"
    assert (capture, heldout, library, twin_dir) == (root / "train", root / "heldout", work / "library", work / "twin")
    assert kw["heldout_views"] == 12 and kw["refine_steps"] == 0 and kw["preset"] == "cpu"
    assert kw["gt"] == json.loads((root / "gt.json").read_text())
    assert "Retrieved 'medium_clamp_cad' (the true model); twin of 1234 splats, preset cpu." in out
    assert "Held-out views (12): fgPSNR 28.33 dB, IoU 0.984, object-crop PSNR 28.31 dB." in out
    assert "1.25 deg / 2.50 % after retrieval, 0.99 deg / 1.11 % after reconstruction" in out
    assert "reconstruction 60.0 s, 30x the anchor (2.00 s a step), evaluation 5 s" in out

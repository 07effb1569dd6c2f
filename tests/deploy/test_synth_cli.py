"""`cadsplat synth`: writes train + held-out captures and gt.json; bad input is one sentence and a non-zero exit."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from PIL import Image

from calibration.capture import read_capture
from calibration.sim3 import Sim3
from deploy.cli import main
from tests.rig.test_synthetic import textured_torus


@pytest.fixture(scope="module")
def torus_obj(tmp_path_factory):
    mesh = textured_torus()
    path = tmp_path_factory.mktemp("mesh") / "torus.obj"
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    tm.visual = trimesh.visual.TextureVisuals(uv=mesh.uv, image=Image.fromarray(mesh.texture))
    tm.export(path)
    return path


def test_synth_writes_captures_and_truth(torus_obj, tmp_path, capsys):
    out = tmp_path / "run"
    rc = main(
        [
            "synth",
            str(torus_obj),
            "--out",
            str(out),
            "--views",
            "4",
            "--heldout",
            "6",
            "--size",
            "96x72",
            "--seed",
            "2",
            "--calib-noise-deg",
            "0.3",
            "--calib-noise-mm",
            "1",
            "--backdrop",
            "--noise",
            "0.01",
        ]
    )
    assert rc == 0
    printed = capsys.readouterr().out
    assert "4 train + 6 held-out views at 96x72" in printed
    train, held = read_capture(out / "train"), read_capture(out / "heldout")
    assert (len(train), len(held)) == (4, 6)
    assert train.frames[0].camera.width == 96 and train.has_masks
    gt = json.loads((out / "gt.json").read_text())
    assert gt["seed"] == 2 and gt["size"] == [96, 72] and gt["render"]["backdrop"]
    assert gt["calib_noise"]["sigma_deg"] == 0.3 and gt["calib_noise"]["sigma_mm"] == 1.0
    sim3 = Sim3.from_dict(gt["sim3_rig_to_object"])
    np.testing.assert_allclose(sim3.apply_to_c2w(np.stack([f.camera.c2w for f in held.frames])), gt["heldout_c2w_object"], atol=1e-9)
    img = train.image(0)
    assert img[~train.mask(0)].std() > 0.03  # backdrop + noise: the background is not flat


@pytest.mark.parametrize(
    "args, words",
    [
        (["--size", "320by240"], "--size must be WIDTHxHEIGHT"),
        (["--size", "4x4"], "--size must be WIDTHxHEIGHT"),
    ],
)
def test_bad_size_is_one_sentence(torus_obj, tmp_path, capsys, args, words):
    rc = main(["synth", str(torus_obj), "--out", str(tmp_path / "o"), *args])
    err = capsys.readouterr().err
    assert rc != 0 and words in err and err.count("\n") == 1
    assert not (tmp_path / "o").exists()


def test_bad_mesh_is_one_sentence(tmp_path, capsys):
    rc = main(["synth", str(tmp_path / "missing.obj"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc != 0 and "missing.obj does not exist" in err and err.count("\n") == 1
    junk = tmp_path / "junk.obj"
    junk.write_bytes(b"\x00\x01garbage")
    rc = main(["synth", str(junk), "--out", str(tmp_path / "o"), "--views", "2", "--heldout", "0", "--size", "32x24"])
    err = capsys.readouterr().err
    assert rc != 0 and "junk.obj" in err and err.strip().count("\n") == 0
    assert not (tmp_path / "o" / "train").exists()


def test_existing_output_is_refused_and_kept(torus_obj, tmp_path, capsys):
    (tmp_path / "o" / "train").mkdir(parents=True)
    (tmp_path / "o" / "train" / "keep.txt").write_text("precious")
    rc = main(["synth", str(torus_obj), "--out", str(tmp_path / "o")])
    assert rc != 0 and "already exists" in capsys.readouterr().err
    assert (tmp_path / "o" / "train" / "keep.txt").read_text() == "precious"

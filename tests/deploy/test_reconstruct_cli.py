"""`cadsplat reconstruct | render | export` end to end on the bundled sample (preview-sized), bad input
in one sentence, and the twin beating its own initial state on held-out views."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

torch.set_num_threads(1)  # the CI box is shared; one thread avoids oversubscription stalls

from calibration.camera import Camera  # noqa: E402
from calibration.capture import FrameData, load_views, read_capture, write_capture  # noqa: E402
from deploy.cli import main  # noqa: E402
from deploy.commands.demo import bundled_sample_dir  # noqa: E402
from reconstruction import presets  # noqa: E402
from reconstruction.twin import load_twin, read_splats_ply  # noqa: E402

SAMPLE = bundled_sample_dir()


@pytest.fixture(scope="module")
def short_preview():
    """The preview preset with short stage caps so a CLI run takes seconds, not a minute."""
    original = presets.resolve_preset

    def resolve(name, stats):
        return replace(original(name, stats), iters_pose=30, iters_deform=20, iters_photo=40, dropout_anneal=20)

    mp = pytest.MonkeyPatch()
    mp.setattr("reconstruction.presets.resolve_preset", resolve)
    yield
    mp.undo()


def test_reconstruct_render_export(tmp_path, library, short_preview, capsys):
    twin_dir = tmp_path / "twin"
    rc = main(
        [
            "reconstruct",
            str(SAMPLE / "train"),
            "--library",
            str(library),
            "--out",
            str(twin_dir),
            "--preset",
            "preview",
            "--views",
            "0,2,4,6,8",
        ]
    )
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "Twin of 'medium_clamp_cad'" in out
    twin = load_twin(twin_dir)
    assert twin.model_id == "medium_clamp_cad" and len(twin.cameras) == 5 and twin.preset == "preview"
    doc = json.loads((twin_dir / "twin.json").read_text())
    for key in (
        "model_id",
        "sim3_rig_to_object_init",
        "sim3_rig_to_object",
        "cameras",
        "preset",
        "choices",
        "timings_s",
        "losses",
        "versions",
    ):
        assert key in doc
    assert {"num_splats", "sh_degree", "pose_mode", "sh_init", "iterations"} <= set(doc["choices"])
    assert all(np.isfinite(v) for v in doc["timings_s"].values())
    assert len(list((twin_dir / "renders").glob("*.png"))) == 5
    assert (twin_dir / "mesh_deformed.glb").exists() and doc["config"]["name"] == "preview" and doc["training"]["views"] == [0, 2, 4, 6, 8]
    assert not any(p.name.endswith(".checkpoint.pt") for p in tmp_path.iterdir())

    # Render held-out cameras: RGBA with alpha = rendered alpha, named after the capture's images.
    held = read_capture(SAMPLE / "heldout")
    rc = main(["render", str(twin_dir), "--views", str(SAMPLE / "heldout"), "--out", str(tmp_path / "r")])
    assert rc == 0
    first = Path(held.frames[0].file_path).stem + ".png"
    img = cv2.imread(str(tmp_path / "r" / first), cv2.IMREAD_UNCHANGED)
    assert img.shape == (240, 320, 4)
    mask = held.mask(0)
    assert (img[..., 3][mask] > 127).mean() > 0.7 and (img[..., 3][~mask] > 127).mean() < 0.05
    assert main(["render", str(twin_dir), "--orbit", "3", "--out", str(tmp_path / "o")]) == 0
    assert len(list((tmp_path / "o").glob("orbit_*.png"))) == 3

    # Exports.
    assert main(["export", str(twin_dir), "--format", "ply", "--out", str(tmp_path / "s.ply")]) == 0
    ply = read_splats_ply(tmp_path / "s.ply")
    np.testing.assert_allclose(ply.means, twin.gaussians.means)
    assert main(["export", str(twin_dir), "--format", "glb", "--out", str(tmp_path / "m.glb")]) == 0
    assert (tmp_path / "m.glb").stat().st_size > 1000


def test_sphere_init_and_ablation_switches(tmp_path, short_preview, capsys):
    """The paper's baselines run through the engine itself: no library is read for the sphere, and the
    ablation leaves the registration's pose untouched."""
    twin_dir = tmp_path / "sphere"
    rc = main(
        [
            "reconstruct",
            str(SAMPLE / "train"),
            "--init",
            "sphere",
            "--ablate",
            "no-pose",
            "--out",
            str(twin_dir),
            "--preset",
            "preview",
            "--views",
            "0,2,4,6,8",
        ]
    )
    assert rc == 0, capsys.readouterr()
    twin = load_twin(twin_dir)
    assert twin.model_id == "sphere" and twin.choices["init"]["value"] == "sphere"
    assert twin.choices["ablations"]["value"] == ["no-pose"]
    # The field carves a sphere into the object, so its stage's cap is longer than from a CAD model (20 here).
    caps = twin.choices["iteration_caps"]
    assert caps["value"]["deform"] == 4 * 20 and "carve" in caps["why"]
    assert twin.sim3_rig_to_object.rotation_deg_to(twin.sim3_rig_to_object_init) == 0.0
    assert 0.2 < twin.choices["registration"]["value"]["score"] < 1.0  # area-matched, so it overlaps the clamp, but is no clamp
    assert main(["reconstruct", str(SAMPLE / "train"), "--out", str(tmp_path / "t")]) != 0
    assert "--library is required" in capsys.readouterr().err


def test_bad_input_is_one_sentence(tmp_path, library, capsys):
    assert main(["reconstruct", str(tmp_path / "nope"), "--library", str(library), "--out", str(tmp_path / "t")]) != 0
    assert main(["reconstruct", str(SAMPLE / "train"), "--library", str(library), "--out", str(tmp_path / "t"), "--views", "a,b"]) != 0
    (tmp_path / "exists").mkdir()
    assert main(["reconstruct", str(SAMPLE / "train"), "--library", str(library), "--out", str(tmp_path / "exists")]) != 0
    assert main(["render", str(tmp_path / "exists"), "--orbit", "3", "--out", str(tmp_path / "o")]) != 0
    assert main(["render", str(tmp_path / "exists"), "--out", str(tmp_path / "o")]) != 0
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert "already exists" in err and "twin.json" in err


@pytest.fixture(scope="module")
def before_after(tmp_path_factory, library):
    """Held-out metrics of the preview twin and of the same splats before training (colours projected at
    the registered poses, field at identity, no pose correction)."""
    from reconstruction.evaluation import evaluate_twin, select_views
    from reconstruction.pipeline import reconstruct_capture

    rec = reconstruct_capture(SAMPLE / "train", library, tmp_path_factory.mktemp("e2e") / "twin", preset="preview")
    twin, s0 = rec.twin, rec.splats
    init = replace(twin, gaussians=s0.gaussians, sim3_rig_to_object=twin.sim3_rig_to_object_init)
    held = read_capture(SAMPLE / "heldout")
    images, masks, cams = load_views(held, select_views(len(held), 8))
    before = evaluate_twin(init, cams, images, masks, refine_steps=0)["mean"]
    after = evaluate_twin(twin, cams, images, masks, refine_steps=0)["mean"]
    print(f"held-out IoU {before['iou']:.3f} -> {after['iou']:.3f}, fgPSNR {before['fgpsnr']:.2f} -> {after['fgpsnr']:.2f} dB")
    return before, after


@pytest.mark.slow
def test_twin_silhouettes_beat_initial_state_on_heldout_views(before_after):
    before, after = before_after
    assert after["iou"] > before["iou"] + 0.02, (before["iou"], after["iou"])


@pytest.mark.slow
def test_twin_colours_beat_initial_state_on_heldout_views(before_after):
    before, after = before_after
    assert after["fgpsnr"] > before["fgpsnr"] + 0.5, (before["fgpsnr"], after["fgpsnr"])


def test_all_white_masks_are_refused_not_a_confident_wrong_twin(tmp_path, library, capsys):
    """Issue 16 (4): all-white masks registered an IMU housing at IoU 1.000 and reconstruct exited 0."""
    from calibration.capture import FrameData, write_capture

    cap = read_capture(SAMPLE / "train")
    frames = [
        FrameData(
            Path(cap.frames[i].file_path).stem,
            (cap.image(i, undistort=False) * 255).round().astype(np.uint8),
            cap.camera(i, undistorted=False),
            cap.frames[i].camera_id,
            None,
            np.ones((cap.frames[i].camera.height, cap.frames[i].camera.width), bool),
        )
        for i in (0, 2, 4, 6)
    ]
    white = write_capture(tmp_path / "white", frames).root
    for argv in (
        ["reconstruct", str(white), "--library", str(library), "--out", str(tmp_path / "twin"), "--preset", "preview"],
        ["register", str(white), "--library", str(library), "--out", str(tmp_path / "reg.json")],
    ):
        assert main(argv) != 0
        err = capsys.readouterr().err.strip()
        assert err.startswith("Error: masks refused: view 0 (") and "covers 100% of the image" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "twin").exists() and not (tmp_path / "reg.json").exists()


@pytest.fixture(scope="module")
def reg_json(tmp_path_factory, library):
    """`cadsplat register` of the sample's training capture."""
    out = tmp_path_factory.mktemp("reg") / "reg.json"
    assert main(["register", str(SAMPLE / "train"), "--library", str(library), "--out", str(out), "--no-overlays"]) == 0
    return out


def test_reconstruct_uses_a_register_output_as_given(tmp_path, library, reg_json, short_preview, monkeypatch, capsys):
    def no_second_registration(*_a, **_k):
        raise AssertionError("reconstruct registered again although it was given a registration")

    monkeypatch.setattr("reconstruction.registration.register", no_second_registration)
    capsys.readouterr()
    rc = main(
        [
            "reconstruct",
            str(SAMPLE / "train"),
            "--library",
            str(library),
            "--registration",
            str(reg_json),
            "--out",
            str(tmp_path / "twin"),
            "--preset",
            "preview",
            "--views",
            "0,2,4,6,8",
        ]
    )
    assert rc == 0, capsys.readouterr().err
    twin = load_twin(tmp_path / "twin")
    reg = json.loads(reg_json.read_text())
    assert twin.model_id == reg["model_id"] and twin.choices["registration"]["source"] == "given"
    np.testing.assert_allclose(twin.sim3_rig_to_object_init.rotation, reg["sim3_rig_to_object"]["rotation"], atol=1e-9)
    assert twin.sim3_rig_to_object_init.scale == pytest.approx(reg["sim3_rig_to_object"]["scale"])


def _refused(argv, capsys) -> str:
    assert main(argv) != 0
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    return err


def test_a_registration_of_another_capture_or_library_is_refused_in_one_sentence(tmp_path, library, reg_json, capsys):
    from calibration.capture import FrameData, write_capture
    from reconstruction.library import build_library

    train, held = read_capture(SAMPLE / "train"), read_capture(SAMPLE / "heldout")
    # Another capture of the rig: as many views, named alike, other photographs and poses.
    frames = [
        FrameData(
            Path(train.frames[i].file_path).stem,
            (held.image(i, undistort=False) * 255).round().astype(np.uint8),
            held.camera(i, undistorted=False),
            train.frames[i].camera_id,
            None,
            held.mask(i, undistort=False),
        )
        for i in range(len(train))
    ]
    other = write_capture(tmp_path / "other", frames, meta={"units": "m"}).root
    fewer = write_capture(tmp_path / "fewer", frames[:4], meta={"units": "m"}).root
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    (meshes / "medium_clamp_cad.ply").write_bytes((SAMPLE / "library_meshes" / "scissors.ply").read_bytes())
    build_library(meshes, tmp_path / "otherlib", progress=False, log=lambda _m: None)

    def run(capture, lib, reg=reg_json):
        return [
            "reconstruct",
            str(capture),
            "--library",
            str(lib),
            "--registration",
            str(reg),
            "--out",
            str(tmp_path / "twin"),
            "--preset",
            "preview",
        ]

    capsys.readouterr()
    assert "was made from another capture than the one at" in _refused(run(other, library), capsys)
    assert "registers 9 camera views but the capture at" in _refused(run(fewer, library), capsys)
    assert "was made with another library" in _refused(run(SAMPLE / "train", tmp_path / "otherlib"), capsys)
    unknown = tmp_path / "unknown.json"
    unknown.write_text(json.dumps({**json.loads(reg_json.read_text()), "model_id": "nonesuch"}))
    assert "registers model 'nonesuch', which is not in the library" in _refused(run(SAMPLE / "train", library, unknown), capsys)
    assert not (tmp_path / "twin").exists()


def test_a_malformed_registration_is_refused_in_one_sentence(tmp_path, library, reg_json, capsys):
    doc = json.loads(reg_json.read_text())
    cases = {
        "garbage.json": "not json {",
        "list.json": "[1, 2]",
        "empty.json": "{}",
        "noscale.json": json.dumps({k: v for k, v in doc.items() if k != "scale"}),
        "badsim3.json": json.dumps({**doc, "sim3_rig_to_object": {**doc["sim3_rig_to_object"], "scale": -1}}),
    }
    capsys.readouterr()
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
        err = _refused(
            [
                "reconstruct",
                str(SAMPLE / "train"),
                "--library",
                str(library),
                "--registration",
                str(tmp_path / name),
                "--out",
                str(tmp_path / "twin"),
            ],
            capsys,
        )
        assert "is not a registration document" in err, err
    assert not (tmp_path / "twin").exists()


def portrait(frame: FrameData) -> FrameData:
    """The same view taken with the camera turned 90 degrees about its optical axis (image turned clockwise)."""
    cam = frame.camera
    (fx, _, cx), (_, fy, cy) = cam.K[0], cam.K[1]
    k = np.array([[fy, 0.0, cam.height - cy], [0.0, fx, cx], [0.0, 0.0, 1.0]])
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # camera axes: x' = -y, y' = x
    c2w = cam.c2w.copy()
    c2w[:3, :3] = cam.c2w[:3, :3] @ turn.T
    camera = Camera(k, cam.height, cam.width, cam.dist, c2w)
    return replace(
        frame, image=np.ascontiguousarray(np.rot90(frame.image, -1)), camera=camera, mask=np.ascontiguousarray(np.rot90(frame.mask, -1))
    )


def test_photos_of_mixed_sizes_train_together(tmp_path, library, short_preview, capsys):
    """A portrait photo among landscape ones is trained on, and the twin fits it at its own size."""
    cap = read_capture(SAMPLE / "train")
    frames = []
    for i in (0, 2, 4, 6, 8):
        image, mask = cap.view(i)
        frames.append(FrameData(f"view{i}", image, cap.camera(i), cap.frames[i].camera_id, None, mask))
    frames[2] = portrait(frames[2])
    mixed = write_capture(tmp_path / "mixed", frames, meta={k: v for k, v in cap.meta.items() if k != "background"})
    twin_dir = tmp_path / "twin"
    rc = main(["reconstruct", str(mixed.root), "--library", str(library), "--out", str(twin_dir), "--preset", "preview"])
    assert rc == 0, capsys.readouterr()
    twin = load_twin(twin_dir)
    assert [(c.camera.width, c.camera.height) for c in twin.cameras] == [(320, 240)] * 2 + [(240, 320)] + [(320, 240)] * 2
    rendered = cv2.imread(str(twin_dir / "renders" / "view4.png"), cv2.IMREAD_UNCHANGED)
    assert rendered.shape == (320, 240, 4)
    drawn, truth = rendered[..., 3] > 127, frames[2].mask
    assert (drawn & truth).sum() / (drawn | truth).sum() > 0.8


def test_like_trains_a_twin_again_from_its_own_record(tmp_path, library, short_preview, capsys):
    """`--like TWIN` takes the recorded configuration, seed, views and registration: the same twin again."""
    first = tmp_path / "first"
    assert (
        main(
            [
                "reconstruct",
                str(SAMPLE / "train"),
                "--library",
                str(library),
                "--out",
                str(first),
                "--preset",
                "preview",
                "--views",
                "1,4,7",
                "--seed",
                "3",
            ]
        )
        == 0
    ), capsys.readouterr().err
    capsys.readouterr()
    again = tmp_path / "again"
    rc = main(["reconstruct", str(SAMPLE / "train"), "--library", str(library), "--out", str(again), "--like", str(first)])
    assert rc == 0, capsys.readouterr().err
    a, b = load_twin(first), load_twin(again)
    assert b.config == a.config and b.training == a.training and b.training["seed"] == 3 and len(b.cameras) == 3
    assert b.choices["registration"]["source"] == "given" and b.model_id == a.model_id
    for name in ("means", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_allclose(getattr(b.gaussians, name), getattr(a.gaussians, name), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(b.sim3_rig_to_object.matrix(), a.sim3_rig_to_object.matrix(), atol=1e-9)
    for stage in ("pose", "deform", "photo"):
        assert b.losses[stage]["total_last_window"] == pytest.approx(a.losses[stage]["total_last_window"], rel=1e-5)
    assert {k: v["value"] for k, v in b.choices.items() if k in a.config} == {k: v["value"] for k, v in a.choices.items() if k in a.config}
    capsys.readouterr()
    assert (
        main(
            [
                "reconstruct",
                str(SAMPLE / "train"),
                "--library",
                str(library),
                "--out",
                str(tmp_path / "x"),
                "--like",
                str(first),
                "--views",
                "0,1",
            ]
        )
        != 0
    )
    assert "--like takes the configuration" in capsys.readouterr().err


def test_a_planted_checkpoint_that_would_run_code_is_refused_not_run(tmp_path, library):
    """A pickle beside the output that runs a command when unpickled: nothing runs, the user reads one sentence."""
    import os
    import pickle
    import subprocess
    import sys

    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    (tmp_path / ".twin.checkpoint.pt").write_bytes(pickle.dumps({"fingerprint": Payload()}))
    repo = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(repo)}
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "deploy.cli",
            "reconstruct",
            str(SAMPLE / "train"),
            "--library",
            str(library),
            "--out",
            str(tmp_path / "twin"),
            "--preset",
            "preview",
            "--views",
            "0,3,6",
        ],
        capture_output=True,
        text=True,
        env=env,
        cwd=repo,
        timeout=900,
        check=False,
    )
    assert out.returncode != 0 and not marker.exists()
    err = out.stderr.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert "is not a checkpoint this engine wrote" in err and not (tmp_path / "twin").exists()

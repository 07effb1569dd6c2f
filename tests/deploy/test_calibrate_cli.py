"""`cadsplat calibrate` end to end as a user runs it: board images -> calibration.json -> checks -> history."""

from __future__ import annotations

import json

import numpy as np

from calibration.board import parse_board
from calibration.camera import Camera
from calibration.capture import FrameData, write_capture
from calibration.fileio import atomic_write_png
from calibration.simulated import render_planes, rig_board_views, rig_frame_scene, ring_rig, sensor
from deploy.cli import main

SPEC = "charuco:11x8:0.025:0.015:DICT_5X5_100"


def test_board_image_and_bad_spec(tmp_path, capsys):
    out = tmp_path / "board.png"
    assert main(["calibrate", "board-image", "--board", "charuco:5x7:0.04:0.02:DICT_6X6_250", "--out", str(out), "--dpi", "127"]) == 0
    from PIL import Image

    im = Image.open(out)
    assert im.size == (5 * 200 + 200, 7 * 200 + 200) and round(im.info["dpi"][0]) == 127
    assert main(["calibrate", "board-image", "--board", "charuco:5x7", "--out", str(out)]) != 0
    assert "is not 'chessboard" in capsys.readouterr().err


def test_board_check_history(tmp_path, capsys):
    rng = np.random.default_rng(5)
    cams = {f"cam{i}": c for i, c in enumerate(ring_rig(3, radius=0.5, arc_deg=60))}
    images, _ = rig_board_views(parse_board(SPEC), cams, rng, shared=8, close_ups=5)
    folders = []
    for name, views in images.items():
        (tmp_path / name).mkdir()
        for frame, img in views.items():
            atomic_write_png(tmp_path / name / f"{frame}.png", img)
        folders += ["--images", str(tmp_path / name)]
    calib = tmp_path / "calibration.json"
    assert main(["calibrate", "board", "--board", SPEC, *folders, "--out", str(calib)]) == 0
    doc = json.loads(calib.read_text())
    assert [c["name"] for c in doc["cameras"]] == ["cam0", "cam1", "cam2"] and doc["version"] == 1
    for c in doc["cameras"]:
        assert c["rms_px"] < 0.2 and np.asarray(c["c2r"]).shape == (4, 4) and "intrinsics_cv_px" in c["uncertainty"]
    assert "up_rig" not in doc  # no frame showed the board lying on the conveyor: nothing guessed
    # A frame named as the board on the conveyor that no camera solved is refused in a sentence, nothing stored.
    assert (
        main(["calibrate", "board", "--board", SPEC, *folders, "--out", str(calib), "--no-cross-validation", "--conveyor-frame", "belt"])
        != 0
    )
    assert "frame 'belt'" in capsys.readouterr().err
    # A second calibration is a new version; the first is kept. Its up comes from the frame named (here one of the
    # tilted board frames: the plumbing, not the physics, which tests/calibration/test_calibfile.py checks).
    assert (
        main(
            ["calibrate", "board", "--board", SPEC, *folders, "--out", str(calib), "--no-cross-validation", "--conveyor-frame", "shared00"]
        )
        == 0
    )
    assert "up (rig frame)" in capsys.readouterr().out
    assert sorted(p.name for p in (tmp_path / "calibration.versions").iterdir()) == ["v0001.json", "v0002.json"]
    up = json.loads(calib.read_text())["up_rig"]

    # Empty-rig capture as reference, then a capture with one camera knocked by 0.15 deg.
    planes, _ = rig_frame_scene(rng, fiducials=False)
    rig_cams = {n: Camera.from_dict({**c, "c2w": c["c2r"]}) for n, c in ((c["name"], c) for c in doc["cameras"])}

    def capture(name: str, knocked: str | None):
        frames = []
        for n, cam in cams.items():
            pose = cam.c2w
            if n == knocked:
                from calibration.so3 import axis_angle_to_matrix

                pose = pose.copy()
                pose[:3, :3] = pose[:3, :3] @ axis_angle_to_matrix(np.radians([0.0, 0.15, 0.0]))
            img = sensor(render_planes(cam.with_c2w(pose), planes, supersample=2), rng)
            frames.append(FrameData(n, np.repeat(img[..., None], 3, 2), rig_cams[n].pinhole(), n))
        return write_capture(tmp_path / name, frames).root

    assert main(["calibrate", "check", str(capture("empty", None)), "--calibration", str(calib), "--set-reference"]) == 0
    assert main(["calibrate", "check", str(capture("cap1", None)), "--calibration", str(calib)]) == 0
    assert main(["calibrate", "check", "--latest", str(tmp_path), "--calibration", str(calib)]) == 0
    knocked = capture("cap2", "cam1")
    assert main(["calibrate", "check", str(knocked), "--calibration", str(calib), "--thorough"]) == 0
    out = capsys.readouterr().out
    assert "cam1: WARN" in out and "cam0: OK" in out and "corrected cam1 as calibration version 3" in out
    assert json.loads(calib.read_text())["up_rig"] == up  # a drift correction keeps the rig frame, so its up
    plot = tmp_path / "drift.png"
    assert main(["calibrate", "history", "--calibration", str(calib), "--plot", str(plot)]) == 0
    out = capsys.readouterr().out
    assert "v0003" in out and "drift-correction" in out and plot.stat().st_size > 1000


def test_errors_are_one_sentence(tmp_path, capsys):
    (tmp_path / "a").mkdir()
    assert main(["calibrate", "board", "--board", SPEC, "--images", str(tmp_path / "a"), "--out", str(tmp_path / "c.json")]) != 0
    assert "holds no images" in capsys.readouterr().err
    assert main(["calibrate", "history", "--calibration", str(tmp_path / "missing.json")]) != 0
    assert "does not exist" in capsys.readouterr().err


def test_check_exits_3_on_recalibrate(tmp_path, capsys):
    from calibration.calibfile import CalibrationDoc, CalibrationStore
    from calibration.so3 import axis_angle_to_matrix

    rng = np.random.default_rng(6)
    cams = {f"cam{i}": c for i, c in enumerate(ring_rig(2, radius=0.5, arc_deg=40))}
    calib = tmp_path / "calibration.json"
    CalibrationStore(calib).commit(CalibrationDoc(dict(cams)))
    planes, _ = rig_frame_scene(rng, fiducials=False)
    for name, deg in (("empty", 0.0), ("bad", 1.0)):
        frames = []
        for n, cam in cams.items():
            pose = cam.c2w.copy()
            if n == "cam1":
                pose[:3, :3] = pose[:3, :3] @ axis_angle_to_matrix(np.radians([deg, 0.0, 0.0]))
            img = sensor(render_planes(cam.with_c2w(pose), planes, supersample=2), rng)
            frames.append(FrameData(n, np.repeat(img[..., None], 3, 2), cam, n))
        write_capture(tmp_path / name, frames)
    assert main(["calibrate", "check", str(tmp_path / "empty"), "--calibration", str(calib), "--set-reference"]) == 0
    assert main(["calibrate", "check", str(tmp_path / "bad"), "--calibration", str(calib)]) == 3
    cap = capsys.readouterr()
    assert "RECALIBRATE: alarm: recalibrate cam1" in cap.out and "recalibrate the rig" in cap.err


def test_wrong_board_spec_is_refused_and_not_stored(tmp_path, capsys):
    """Issue 16 (3): a 7x5 spec on the 9x6 photos used to store version 1 with an RMS of pixels."""
    from tests.conftest import require_shared

    photos = require_shared("calibration", "opencv_chessboard")
    folder = tmp_path / "left"
    folder.mkdir()
    for p in sorted(photos.glob("left*.jpg")):
        (folder / p.name).write_bytes(p.read_bytes())
    calib = tmp_path / "calibration.json"
    args = ["calibrate", "board", "--board", "chessboard:7x5:0.025", "--images", str(folder), "--out", str(calib), "--no-cross-validation"]
    assert main(args) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("Error: calibration refused and not stored: camera 'left' reprojects with RMS") and len(err.splitlines()) == 1
    assert not calib.exists() and not (tmp_path / "calibration.versions").exists()
    assert main(args + ["--force"]) == 0
    doc = json.loads(calib.read_text())
    assert doc["version"] == 1 and "reprojects with RMS" in doc["notes"]["forced"][0]
    assert "FORCED past the quality gate" in capsys.readouterr().out


def test_quality_gate_names_each_implausible_figure():
    from calibration.calibfile import CalibrationDoc, quality_problems

    good = Camera.from_fov(np.radians(60), 640, 480)
    assert quality_problems(CalibrationDoc({"a": good}, {"a": {"rms_px": 0.3, "coverage": 0.6}})) == []
    k = good.K.copy()
    k[1, 2] = 1305.0
    bad = Camera(k, 640, 480, np.zeros(0), good.c2w)
    problems = quality_problems(CalibrationDoc({"a": bad}, {"a": {"rms_px": 76.6, "coverage": 0.05}}))
    assert [p.split(" ")[2] for p in problems] == ["reprojects", "has", "saw"]
    assert "principal point at (320, 1305) px" in problems[1]

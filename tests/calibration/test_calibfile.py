"""calibration.json states its scale: a board calibration is metric (`units: m`), an SfM one is not."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibration.calibfile import (
    CalibrationDoc,
    CalibrationFileError,
    CalibrationStore,
    read_calibration,
)
from calibration.camera import Camera


def cams() -> dict[str, Camera]:
    k = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
    return {"cam0": Camera(k, 64, 48, np.zeros(0), np.eye(4))}


def test_board_calibration_says_metric_and_sfm_says_unknown(tmp_path):
    board = CalibrationStore(tmp_path / "board.json").commit(CalibrationDoc(cams(), source="board"))
    doc = json.loads((tmp_path / "board.json").read_text())
    assert board.units == "m" and doc["units"] == "m" and doc["scale"].startswith("metric")
    # A drift correction keeps the frame, so it keeps the units.
    assert board.with_cameras(cams(), source="drift-correction").units == "m"

    CalibrationStore(tmp_path / "sfm.json").commit(CalibrationDoc(cams(), source="sfm"))
    doc = json.loads((tmp_path / "sfm.json").read_text())
    assert "units" not in doc and doc["scale"].startswith("unknown")
    assert read_calibration(tmp_path / "sfm.json").units is None


def test_a_calibration_in_units_it_does_not_know_is_refused_where_it_is_loaded(tmp_path):
    CalibrationStore(tmp_path / "c.json").commit(CalibrationDoc(cams(), source="board"))
    doc = json.loads((tmp_path / "c.json").read_text())
    for bad in ("meters", ["m"]):
        (tmp_path / "c.json").write_text(json.dumps({**doc, "units": bad}))
        with pytest.raises(CalibrationFileError) as e:
            read_calibration(tmp_path / "c.json")
        assert str(e.value).startswith(f"{tmp_path / 'c.json'}: units {bad!r} is not a unit cadsplat knows (one of m, mm, cm, in")
    (tmp_path / "c.json").write_text(json.dumps({**doc, "units": "mm"}))
    assert read_calibration(tmp_path / "c.json").units == "mm"


def test_a_board_lying_on_the_conveyor_gives_the_rigs_up_and_the_file_keeps_it(tmp_path):
    """The frame named `conveyor` (the board lying printed face up on the belt, z = 0 of a z-up world) gives the rig's
    up, in the rig frame (the first camera's): the world's +z seen from that camera. Stored and read back; a
    named frame the calibration did not solve is refused in a sentence."""
    from calibration.board import detect_board, parse_board
    from calibration.calibfile import CONVEYOR_FRAME, from_rig
    from calibration.camera import invert_rigid
    from calibration.multiview import calibrate_rig
    from calibration.simulated import board_plane, render_planes, rig_board_views, ring_rig, sensor

    spec = parse_board("charuco:11x8:0.025:0.015:DICT_5X5_100")
    rng = np.random.default_rng(1)
    cameras = {f"cam{i}": c for i, c in enumerate(ring_rig(3, radius=0.45, arc_deg=60, height_m=0.35))}
    images, _ = rig_board_views(spec, cameras, rng, shared=10, close_ups=4)
    flat = np.eye(4)
    flat[:3, :3] = np.diag([1.0, -1.0, -1.0])  # face up: board x along world x, its z (into the board) down
    flat[:3, 3] = -flat[:3, :3] @ np.array([spec.size_m[0] / 2, spec.size_m[1] / 2, 0.0])
    for name, cam in cameras.items():
        images[name][CONVEYOR_FRAME] = sensor(render_planes(cam, [board_plane(spec, flat)], supersample=2), rng)
    dets = {n: {f: detect_board(spec, im) for f, im in v.items()} for n, v in images.items()}
    assert all(dets[n][CONVEYOR_FRAME] is not None for n in cameras)
    rig = calibrate_rig(dets, {n: (640, 480) for n in dets}, cross_validate=False)

    doc = CalibrationStore(tmp_path / "calibration.json").commit(from_rig(rig, board=str(spec)))
    truth = invert_rigid(cameras["cam0"].c2w)[:3, :3] @ [0.0, 0.0, 1.0]
    up = read_calibration(tmp_path / "calibration.json").up_rig
    assert up == doc.up_rig and up["source"] == "calibration" and CONVEYOR_FRAME in up["detail"]
    assert np.degrees(np.arccos(np.clip(np.dot(up["vector"], truth), -1.0, 1.0))) < 0.1
    with pytest.raises(CalibrationFileError, match="frame 'belt'"):
        from_rig(rig, board=str(spec), conveyor_frame="belt")
    # Without a conveyor frame nothing is guessed.
    del rig.board_to_rig[CONVEYOR_FRAME]
    assert from_rig(rig, board=str(spec)).up_rig is None


def test_a_malformed_up_is_refused_where_the_calibration_is_loaded(tmp_path):
    CalibrationStore(tmp_path / "calibration.json").commit(CalibrationDoc(cams(), source="board"))
    doc = json.loads((tmp_path / "calibration.json").read_text())
    for bad in ({"vector": [0, 0, 0]}, {"vector": [0, 1]}, {"vector": [0, 0, 2]}, [0, 0, 1]):
        (tmp_path / "bad.json").write_text(json.dumps({**doc, "up_rig": bad}))
        with pytest.raises(CalibrationFileError, match="up_rig"):
            read_calibration(tmp_path / "bad.json")

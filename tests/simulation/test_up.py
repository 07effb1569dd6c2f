"""Which way is up: the precedence of its sources and the rotations that stand a part on it."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.board import board_up
from reconstruction.mesh_io import Z_UP_TO_Y_UP
from simulation.up import axis_vector, capture_up, resolve_up, rotation_between, standing, usd_up_axis


def test_sources_in_order_twin_calibration_rig_toml_cad_then_default():
    turn = Rotation.from_euler("x", 90, degrees=True).as_matrix()  # rig z -> object -y
    up = resolve_up(twin_up={"vector": [0, 2, 0], "source": "calibration"}, rig_up=[0, 0, 1], rotation_rig_to_object=turn, cad_up_axis="z")
    # The twin's record wins and keeps the source it was measured from.
    assert up.source == "calibration" and up.vector == pytest.approx([0, 1, 0]) and "recorded in twin.json" in up.detail
    up = resolve_up(calibration_up=[0, 1, 0], rig_up=[0, 0, 1], rotation_rig_to_object=turn)
    assert up.source == "calibration" and up.vector == pytest.approx([0, 0, 1])
    up = resolve_up(rig_up=[0, 0, 1], rotation_rig_to_object=turn, cad_up_axis="z")
    assert up.source == "rig.toml" and up.vector == pytest.approx([0, -1, 0])
    up = resolve_up(cad_up_axis="+y")
    assert up.source == "cad" and up.vector == pytest.approx([0, 1, 0])
    up = resolve_up()
    assert up.source == "default" and up.vector == pytest.approx([0, 0, 1]) and "assumed" in up.detail


def test_standing_turns_up_onto_the_target_and_z_up_to_y_up_is_gltfs_usual_turn():
    assert standing(np.array([0, 0, 1.0]), "+y") == pytest.approx(Z_UP_TO_Y_UP[:3, :3])
    assert standing(np.array([0, 1.0, 0]), "+y") == pytest.approx(np.eye(3))
    rng = np.random.default_rng(0)
    for a in [*rng.normal(size=(20, 3)), np.array([0, -1.0, 0]), np.array([0, 0, -1.0])]:
        for target in ("+y", "+z"):
            r = standing(a, target)
            assert r @ r.T == pytest.approx(np.eye(3)) and np.linalg.det(r) == pytest.approx(1.0)
            assert r @ (a / np.linalg.norm(a)) == pytest.approx(axis_vector(target), abs=1e-12)
    assert rotation_between(np.array([1.0, 0, 0]), np.array([-1.0, 0, 0])) @ [1, 0, 0] == pytest.approx([-1, 0, 0])


def test_board_lying_face_up_gives_the_rig_up_and_usd_takes_the_nearer_axis():
    board = np.eye(4)
    board[:3, :3] = Rotation.from_euler("x", 180, degrees=True).as_matrix()  # printed face up: its z points down
    assert board_up(board) == pytest.approx([0, 0, 1])
    assert usd_up_axis(np.array([0.1, 0.9, 0.2])) == "Y" and usd_up_axis(np.array([0.0, 0.3, 0.9])) == "Z"


def test_bad_axes_are_refused_in_a_sentence():
    for bad in ("w", "++y", "", "yz"):
        with pytest.raises(ValueError, match="up axis"):
            axis_vector(bad)
    with pytest.raises(ValueError, match="non-zero"):
        resolve_up(twin_up={"vector": [0, 0, 0]})


def test_a_capture_carries_the_calibrations_up_else_rig_tomls_else_none():
    measured = {"vector": [0.0, 0.0, 1.0], "source": "calibration", "detail": "board frame 'conveyor' lying face up on the conveyor"}
    assert capture_up(measured, [0, 1, 0]) == measured
    up = capture_up(None, [0, 0, 2])
    assert up["source"] == "rig.toml" and up["vector"] == [0.0, 0.0, 1.0]
    assert capture_up(None, None) is None
    with pytest.raises(ValueError, match="simulation.up"):
        capture_up(None, [0, 0, 0])

"""`cadsplat simulate`: the paper's demo on small twins — drop one twin onto another, let it come to
rest, render the Gaussians following the bodies — and bad input answered in one sentence."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pytest

from calibration.so3 import quat_to_matrix
from deploy.cli import main
from reconstruction.twin import load_twin
from simulation.follow import camera_path
from simulation.scene import load_scene
from tests.simulation.twins import hammer, make_twin, skateboard

SCENE = """
duration = 1.6
fps = 10
[camera]
mode = "turntable"
eye = [0.32, -0.32, 0.22]
target = [0, 0, 0.04]
width = 128
height = 96
fov_deg = 50
turns = 0.2
[[twin]]
name = "board"
path = "twins/board"
bottom = 0.0
material = "wood"
[[twin]]
name = "hammer"
path = "twins/hammer"
pos = [0.0, 0.0, 0.0]
euler_deg = [0, 12, 30]
bottom = 0.09
material = "steel"
"""


@pytest.fixture(scope="module")
def drop_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("sim")
    make_twin(root / "twins", "board", *skateboard(), n=2500)
    make_twin(root / "twins", "hammer", *hammer(), n=2000, seed=1)
    (root / "scene.toml").write_text(SCENE)
    code = main(["simulate", str(root / "scene.toml"), "--out", str(root / "out")])
    return root, code


def world(vertices, pos, quat):
    return vertices @ quat_to_matrix(np.asarray(quat)).T + np.asarray(pos)


def test_upper_twin_comes_to_rest_on_the_lower(drop_run):
    root, code = drop_run
    assert code == 0
    poses = json.loads((root / "out" / "poses.json").read_text())
    assert set(poses["bodies"]) == {"board", "hammer"}
    board, ham = poses["bodies"]["board"], poses["bodies"]["hammer"]
    deck = load_twin(root / "twins" / "board").load_mesh_deformed()
    deck_v = deck.vertices[deck.faces[deck.face_part == deck.part_names.index("deck")].reshape(-1)]
    deck_top = world(deck_v, board["pos"][-1], board["quat_wxyz"][-1])[:, 2].max()
    hv = load_twin(root / "twins" / "hammer").load_mesh_deformed().vertices
    start = world(hv, ham["pos"][0], ham["quat_wxyz"][0])[:, 2]
    end = world(hv, ham["pos"][-1], ham["quat_wxyz"][-1])[:, 2]
    assert start.min() == pytest.approx(0.09, abs=1e-6)  # placed as the scene says
    assert end.min() > deck_top - 1e-3  # resting on the deck, not through it
    assert end.min() < deck_top + 0.03  # and it did fall onto it
    assert poses["kinetic_energy_j"][-1] < 1e-3 * max(poses["kinetic_energy_j"])
    assert poses["penetration_m"][-1] <= 1e-3


def test_frames_and_gif_show_the_fall(drop_run):
    root, _ = drop_run
    out = root / "out"
    frames = sorted((out / "frames").glob("frame_*.png"))
    assert len(frames) == 17
    gif = iio.imread(out / "simulation.gif", index=None)
    assert gif.shape[0] == 17 and gif.shape[1:3] == (96, 128)
    first, last = iio.imread(frames[0]).astype(float), iio.imread(frames[-1]).astype(float)
    assert np.abs(first - last).mean() > 2.0  # the hammer fell and the camera turned
    # The hammer's final centre projects onto object pixels (not the white background).
    scene = load_scene(root / "scene.toml")
    cam = camera_path(scene.camera, 17)[-1]
    ham = json.loads((out / "poses.json").read_text())["bodies"]["hammer"]
    hv = load_twin(root / "twins" / "hammer").load_mesh_deformed().vertices
    uv, _ = cam.project(world(hv, ham["pos"][-1], ham["quat_wxyz"][-1]).mean(0, keepdims=True))
    u, v = uv[0]
    patch = last[int(v) - 1 : int(v) + 2, int(u) - 1 : int(u) + 2]
    assert patch.mean() < 235
    assert (out / "mjcf" / "model.xml").exists() and (out / "mjcf" / "manifest.json").exists()


def test_bad_inputs_are_one_sentence(tmp_path, capsys):
    assert main(["simulate", str(tmp_path / "none.toml"), "--out", str(tmp_path / "o")]) != 0
    assert "no such scene file" in capsys.readouterr().err
    (tmp_path / "bad.toml").write_text("[[twin]]\npath = 'missing'\n")
    assert main(["simulate", str(tmp_path / "bad.toml"), "--out", str(tmp_path / "o")]) != 0
    assert "does not exist" in capsys.readouterr().err
    (tmp_path / "part.stl").write_bytes(b"")
    (tmp_path / "odd.toml").write_text("[[twin]]\npath = 'part.stl'\nspin = 3\n")
    assert main(["simulate", str(tmp_path / "odd.toml"), "--out", str(tmp_path / "o")]) != 0
    assert "unknown key 'spin'" in capsys.readouterr().err
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("precious")
    (tmp_path / "ok.toml").write_text("[[twin]]\npath = 'part.stl'\nunit = 'mm'\n")
    assert main(["simulate", str(tmp_path / "ok.toml"), "--out", str(tmp_path / "full")]) != 0
    assert "already holds files" in capsys.readouterr().err
    assert (tmp_path / "full" / "keep.txt").read_text() == "precious"

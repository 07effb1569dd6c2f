"""scene.toml: every size that drives an allocation or a loop is bounded, refused in one sentence naming its key (issue 58, 16)."""

from __future__ import annotations

import pytest

from deploy.cli import main
from simulation.scene import MAX_FRAME_PIXELS, SceneError, parse_scene


def _doc(twin: dict | None = None, **top) -> dict:
    return {"twin": [{"path": "m.stl", **(twin or {})}], **top}


@pytest.fixture
def base(tmp_path):
    (tmp_path / "m.stl").write_bytes(b"")
    return tmp_path


def test_values_within_their_bounds_are_kept(base):
    scene = parse_scene(_doc({"splats": 1_000_000}, duration=600.0, fps=5, timestep=0.001, camera={"width": 640, "height": 240}), base)
    assert (scene.duration, scene.fps, scene.placements[0].splats, scene.camera.width) == (600.0, 5.0, 1_000_000, 640)


@pytest.mark.parametrize(
    "doc, message",
    [
        (_doc({"splats": 10**9}), r"twin #1 splats must be at most 1000000 \(splats per twin"),
        (_doc({"splats": 2.5e4}), r"twin #1 splats must be a whole number, got 25000\.0"),
        (_doc({"splats": "many"}), r"twin #1 splats must be a whole number"),
        (_doc(duration=1e9), r"duration must be at most 600 \(s; ten minutes"),
        (_doc(duration=float("inf")), r"duration must be a positive number"),
        (_doc(fps=1e6), r"fps must be at most 240"),
        (_doc(fps=0), r"fps must be a positive number"),
        (_doc(timestep=1e-9), r"timestep must be at least 1e-05 s"),
        (_doc(timestep=5.0), r"timestep must be at most 0\.1"),
        (_doc(duration=600.0, timestep=1e-5), r"duration / timestep is 6e\+07 physics steps; at most 10,000,000"),
        (_doc(camera={"width": 100000}), r"camera width must be at most 4096"),
        (_doc(camera={"height": 240.5}), r"camera height must be a whole number"),
        (
            _doc(duration=600.0, fps=240, camera={"width": 1920, "height": 1080}),
            r"rendered pixels, held for the video; at most 500,000,000",
        ),
        (_doc(floor={"size": 1e12}), r"floor size must be at most 1000"),
        ({"twin": [{"path": "m.stl", "name": f"t{i}"} for i in range(101)]}, r"has 101 \[\[twin\]\] entries; at most 100"),
        ({"twin": [3]}, r"each \[\[twin\]\] must be a table"),
        (_doc(camera=[1]), r"\[floor\] and \[camera\] must be tables"),
    ],
)
def test_sizes_past_their_bounds_are_one_sentence(base, doc, message):
    with pytest.raises(SceneError, match=message) as err:
        parse_scene(doc, base)
    assert "\n" not in str(err.value)


def test_the_frame_budget_is_what_the_video_holds(base):
    """(duration x fps + 1) frames of width x height uint8 RGB: the default 320x240 camera has 6510 frames of budget."""
    frames = MAX_FRAME_PIXELS // (320 * 240)
    parse_scene(_doc(duration=(frames - 1) / 25, fps=25), base)
    with pytest.raises(SceneError, match="rendered pixels"):
        parse_scene(_doc(duration=(frames + 1) / 25, fps=25), base)


def test_simulate_refuses_a_runaway_scene_in_one_sentence(base, capsys):
    (base / "scene.toml").write_text('duration = 2.0\nfps = 25\n[[twin]]\npath = "m.stl"\nsplats = 2000000000\n')
    rc = main(["simulate", str(base / "scene.toml"), "--out", str(base / "out")])
    captured = capsys.readouterr()
    assert rc != 0 and "Traceback" not in captured.err + captured.out
    assert len(captured.err.strip().splitlines()) == 1 and "splats must be at most" in captured.err
    assert not (base / "out").exists()

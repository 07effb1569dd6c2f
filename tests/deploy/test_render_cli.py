"""`cadsplat render --list-parts / --explode / --hide-part` on a small multi-part twin."""

import numpy as np
from PIL import Image

from deploy.cli import main
from tests.simulation.twins import make_twin, skateboard


def test_list_explode_and_hide_parts(tmp_path, capsys):
    parts, face_rgb = skateboard()
    twin = make_twin(tmp_path, "skateboard", parts, face_rgb)
    assert main(["render", str(twin), "--list-parts"]) == 0
    listing = capsys.readouterr().out
    assert all(name in listing for name in parts.part_names)

    assert main(["render", str(twin), "--orbit", "1", "--out", str(tmp_path / "whole")]) == 0
    assert main(["render", str(twin), "--orbit", "1", "--explode", "0.8", "--out", str(tmp_path / "exploded")]) == 0
    hidden = parts.part_names[-1]
    assert main(["render", str(twin), "--orbit", "1", "--hide-part", hidden, "--out", str(tmp_path / "hidden")]) == 0
    alpha = {k: np.asarray(Image.open(tmp_path / k / "orbit_000.png"))[..., 3] > 127 for k in ("whole", "exploded", "hidden")}
    # Exploding spreads the silhouette; hiding a part removes pixels, never adds them.
    assert alpha["exploded"].sum() != alpha["whole"].sum() and (alpha["exploded"] & ~alpha["whole"]).any()
    assert alpha["hidden"].sum() < alpha["whole"].sum() and not (alpha["hidden"] & ~alpha["whole"]).any()

    assert main(["render", str(twin), "--orbit", "1", "--hide-part", "no-such-part", "--out", str(tmp_path / "x")]) != 0
    assert "no part named 'no-such-part'" in capsys.readouterr().err


def test_refining_against_a_capture_masks_it_once_not_per_view(tmp_path, monkeypatch):
    import reconstruction.masks
    from calibration.camera import Camera, look_at_c2w
    from calibration.capture import FrameData, write_capture

    parts, face_rgb = skateboard()
    twin = make_twin(tmp_path, "skateboard", parts, face_rgb, n=500)
    rng = np.random.default_rng(0)
    frames, backgrounds = [], {}
    for i in range(3):
        cam = Camera.from_fov(np.radians(50), 64, 48, look_at_c2w(np.array([np.cos(2 * i), np.sin(2 * i), 0.5]), np.zeros(3)))
        empty = rng.integers(90, 110, (48, 64, 3), dtype=np.uint8)
        photo = empty.copy()
        photo[16:32, 24:40] = (200, 60, 40)
        frames.append(FrameData(f"cam{i}", photo, cam, f"cam{i}"))
        backgrounds[f"cam{i}"] = empty
    capture = write_capture(tmp_path / "capture", frames, backgrounds=backgrounds).root
    calls = []
    original = reconstruction.masks.capture_masks
    monkeypatch.setattr(reconstruction.masks, "capture_masks", lambda *a, **k: (calls.append(1), original(*a, **k))[1])
    assert main(["render", str(twin), "--views", str(capture), "--refine-steps", "1", "--out", str(tmp_path / "r")]) == 0
    assert len(calls) == 1 and len(list((tmp_path / "r").glob("cam*.png"))) == 3

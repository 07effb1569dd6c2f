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

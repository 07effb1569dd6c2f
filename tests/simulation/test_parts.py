"""Parts: splats inherit their face's part, exploded views move the chosen parts away from the
assembly centre and leave the rest exactly where they were."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera import Camera, look_at_c2w
from calibration.fileio import atomic_write_png
from reconstruction.twin import load_twin
from simulation.follow import render_bodies
from simulation.parts import exploded_splats, list_parts, part_centroids, splat_parts
from tests.simulation.twins import make_twin, skateboard


@pytest.fixture(scope="module")
def board(tmp_path_factory):
    return load_twin(make_twin(tmp_path_factory.mktemp("twins"), "board", *skateboard(), n=4000))


def test_splats_inherit_their_face_part():
    assert list(splat_parts(np.array([2, 0, 1, 2]), np.array([5, 6, 7]))) == [7, 5, 6, 7]


def test_list_and_hide_parts(board):
    listed = list_parts(board)
    assert [name for _, name, _ in listed] == ["deck", "wheel_0", "wheel_1", "wheel_2", "wheel_3"]
    assert sum(n for _, _, n in listed) == board.num_splats
    out, labels = exploded_splats(board, 0.0, hidden=["wheel_1", 4])  # by name (index 2) and by index
    assert set(np.unique(labels).tolist()) == {0, 1, 3}
    assert out.means == pytest.approx(board.gaussians.means[~np.isin(board.part_label, [2, 4])])
    with pytest.raises(ValueError, match="no part named 'axle'"):
        exploded_splats(board, 0.5, hidden=["axle"])
    with pytest.raises(ValueError, match="factor"):
        exploded_splats(board, -1.0)


def test_explode_moves_wheels_and_keeps_the_deck(board):
    p = len(board.part_names)
    means = board.gaussians.means
    before = part_centroids(means, board.part_label, p)
    out, labels = exploded_splats(board, 0.5, moving=["wheel_0", "wheel_1", "wheel_2", "wheel_3"])
    after = part_centroids(out.means, labels, p)
    centre = before.mean(0)
    assert np.array_equal(out.means[board.part_label == 0], means[board.part_label == 0])  # deck fixed
    for w in range(1, 5):
        assert after[w] - centre == pytest.approx(1.5 * (before[w] - centre), abs=1e-6)
    # Every splat of a part moves by the same vector: parts move rigidly.
    shift = out.means - means
    for w in range(1, 5):
        assert np.ptp(shift[board.part_label == w], 0).max() < 1e-6


def red_pixels(rgb):
    return np.argwhere((rgb[..., 0] > 0.6) & (rgb[..., 1] < 0.35) & (rgb[..., 2] < 0.35))


def green_pixels(rgb):
    return np.argwhere((rgb[..., 1] > 0.45) & (rgb[..., 0] < 0.3))


def test_exploded_view_render(board, tmp_path):
    # Seen from below the side so the wheels are in view; the exploded view is written as a PNG.
    cam = Camera.from_fov(np.deg2rad(55), 160, 120, look_at_c2w(np.array([0.05, -0.42, -0.12]), np.array([0, 0, 0.02])))
    assembled, _ = render_bodies([board.gaussians], [np.eye(4)], cam)
    exploded, _ = render_bodies([exploded_splats(board, 0.8, moving=[f"wheel_{i}" for i in range(4)])[0]], [np.eye(4)], cam)
    atomic_write_png(tmp_path / "exploded.png", np.concatenate([assembled, exploded], 1))
    r0, r1 = red_pixels(assembled), red_pixels(exploded)
    g0, g1 = green_pixels(assembled), green_pixels(exploded)
    assert len(r0) > 30 and len(r1) > 30 and len(g0) > 200
    # Wheels spread out in the image; the deck stays where it was.
    centre = np.array([60, 80])
    assert np.abs(r1 - centre).mean(0)[1] > 1.3 * np.abs(r0 - centre).mean(0)[1]
    assert np.abs(g1.mean(0) - g0.mean(0)).max() < 2.0
    assert (tmp_path / "exploded.png").stat().st_size > 1000

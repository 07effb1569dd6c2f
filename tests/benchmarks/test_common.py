import numpy as np
import trimesh

from benchmarks._common import symmetric_surface_distance


def test_surface_distance_is_zero_on_one_surface_and_the_offset_between_two():
    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    v, f = np.asarray(ball.vertices), np.asarray(ball.faces)
    same, _ = symmetric_surface_distance(v, f, v, f, 5000)
    assert same < 1e-7  # two samplings of one surface: no floor from the sampling
    mean, p95 = symmetric_surface_distance(v, f, v * 1.02, f, 5000)
    assert abs(mean - 0.001) < 5e-5 and abs(p95 - 0.001) < 5e-5  # a 2 % larger ball lies 1 mm out everywhere

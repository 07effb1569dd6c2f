import numpy as np
import trimesh

from benchmarks._common import cpu_line, symmetric_surface_distance


def test_surface_distance_is_zero_on_one_surface_and_the_offset_between_two():
    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    v, f = np.asarray(ball.vertices), np.asarray(ball.faces)
    same, _ = symmetric_surface_distance(v, f, v, f, 5000)
    assert same < 1e-7  # two samplings of one surface: no floor from the sampling
    mean, p95 = symmetric_surface_distance(v, f, v * 1.02, f, 5000)
    assert abs(mean - 0.001) < 5e-5 and abs(p95 - 0.001) < 5e-5  # a 2 % larger ball lies 1 mm out everywhere


def test_cpu_line_names_the_vector_width_and_bfloat16_that_move_the_timings():
    zen3 = "processor\t: 0\nmodel name\t: AMD EPYC\nflags\t\t: fpu sse avx fma avx2\n\nprocessor\t: 1\nmodel name\t: AMD EPYC\n"
    spr = "model name\t: Intel(R) Xeon(R) Platinum 8488C\nflags\t\t: avx2 avx512f avx512_bf16 amx_bf16 amx_tile\n"
    assert cpu_line(zen3).startswith("AMD EPYC, ") and cpu_line(zen3).endswith(", AVX2 (no AVX-512), no native bfloat16")
    assert cpu_line(spr).endswith(", AVX-512, native bfloat16")
    assert cpu_line("").startswith("unknown CPU, ") and cpu_line("").endswith("no AVX2, no native bfloat16")

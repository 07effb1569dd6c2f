import numpy as np
import trimesh

import benchmarks._common as common
from benchmarks._common import MachineReading, cpu_line, median_x_anchor, symmetric_surface_distance, x_anchor


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


def test_x_anchor_is_the_time_over_the_anchor_step_at_two_significant_figures_or_a_dash_when_unknown():
    assert x_anchor(38.1, 1410.0) == "27.0x"
    assert x_anchor(141.0, 1000.0) == "141x"
    assert x_anchor(0.052, 1000.0) == "0.052x" and x_anchor(0.52, 1000.0) == "0.52x"
    assert x_anchor(2.661, 2674.0) == "1.00x"  # two decimals below 1x: never rounded up to a bare "1"
    assert x_anchor(12.0, None) == "-" and x_anchor(None, 1000.0) == "-" and x_anchor(float("nan"), 1000.0) == "-"


def test_median_x_anchor_pairs_each_time_with_its_own_reading_and_leaves_out_runs_without_one():
    assert median_x_anchor([(10.0, 1000.0), (40.0, 2000.0), (99.0, None)]) == "15.0x"  # 10x and 20x; not 50 s / 1.5 s
    assert median_x_anchor([(30.0, 1000.0)]) == "30.0x"
    assert median_x_anchor([(12.0, None)]) == "-" and median_x_anchor([]) == "-"


def test_machine_reading_reads_the_load_before_the_anchor_and_states_all_three(monkeypatch):
    calls = []
    monkeypatch.setattr(common, "load_line", lambda: calls.append("load") or "load average 1.0 on 2 cores")
    monkeypatch.setattr("reconstruction.render.anchor.anchor_ms", lambda: calls.append("anchor") or 1234.4)
    reading = common.machine_reading()
    assert calls == ["load", "anchor"]  # the anchor's child process would otherwise load the cores it reads
    assert reading.anchor_ms == 1234.4 and reading.x_anchor(12.344) == "10.0x"
    header = reading.header()
    assert "1234 ms a step" in header and reading.cpu in header and "load average 1.0 on 2 cores" in header
    assert MachineReading(**vars(reading)) == reading  # a plain record: cached runs store it as JSON


def test_a_results_file_rewritten_keeps_the_sections_people_wrote_once_and_replaces_its_own(tmp_path):
    from benchmarks._common import write_results

    path = tmp_path / "results" / "r.md"
    assert write_results(path, "# T\n\n## map `a`\n\nnew\n") == path.read_text() == "# T\n\n## map `a`\n\nnew\n"
    path.write_text("# T\n\nold intro\n\n## map `a`\n\nold table\n\n## Reading (by hand)\n\nkept\n\n### detail\n\nkept too\n")
    text = write_results(path, "# T\n\n## map `a`\n\nnew table\n")
    assert text == path.read_text() == "# T\n\n## map `a`\n\nnew table\n\n## Reading (by hand)\n\nkept\n\n### detail\n\nkept too\n"
    assert write_results(path, "# T\n\n## map `a`\n\nnew table\n") == text

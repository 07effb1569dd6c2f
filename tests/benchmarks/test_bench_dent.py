"""The dent benchmark's markdown: each wall time stands beside its ratio to the anchor read in the same run."""

from __future__ import annotations

from benchmarks._common import MachineReading
from benchmarks.bench_dent import SOURCE, write_markdown


def test_the_wall_times_carry_their_ratio_to_the_anchor_and_the_header_states_the_reading(tmp_path):
    part = {
        "line": "PASS",
        "exit_code": 0,
        "distance_to_dent_mm": None,
        "patch_mean_deviation_mm": None,
        "patch_seen_vertices": 0,
        "max_abs_away_from_dent_mm": 0.4,
        "unseen_pct": 3.0,
    }
    res = {
        "part": str(SOURCE),
        "model_id": "050_medium_clamp",
        "dent_centre_mm": [1.0, 2.0, 3.0],
        "depth_mm": 2.0,
        "radius_mm": 8.0,
        "views": 9,
        "preset": "preview",
        "tolerance_mm": 1.5,
        "max_unseen_pct": 10.0,
        "nominal": part,
        "dented": part,
        "timings_s": {"synth_and_library_s": 20.0, "reconstruct_nominal_s": 40.0, "reconstruct_dented_s": 42.0},
    }
    machine = MachineReading(2000.0, "AMD EPYC, 2 cores, AVX2 (no AVX-512), no native bfloat16", "load average 1.5 on 2 cores")
    text = write_markdown(res, machine, "1-min load average 2.0 on 2 cores", tmp_path / "dent.md")
    assert "synthesis + library 20 s (10.0x)" in text and "40 s (20.0x) (nominal)" in text and "42 s (21.0x) (dented)" in text
    assert "2000 ms a step" in text and machine.cpu in text and machine.load in text
    assert (tmp_path / "dent.md").read_text() == text

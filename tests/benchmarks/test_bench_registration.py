"""The registration report: scene, grid and scale times beside their ratio to the run's anchor reading, the
library's build time against the reading of the run that built it."""

from __future__ import annotations

from benchmarks._common import MachineReading
from benchmarks.bench_registration import write_report


def test_every_time_in_the_report_carries_its_ratio(tmp_path):
    machine = MachineReading(2000.0, "AMD EPYC, 2 cores, AVX2 (no AVX-512), no native bfloat16", "load average 1.5 on 2 cores")
    scene = {"scene": "00_banana", "views": 9, "chosen": "banana_cad", "correct": True, "rot_deg": 1.0, "ctr_pct": 2.0}
    scene |= {"rot_sym_deg": 1.0, "ctr_sym_pct": 2.0, "iou": 0.9, "ambiguous": False, "time_s": 4.0}
    scene |= {"indep_rot_deg": 5.0, "indep_ctr_pct": 9.0, "indep_right_model": 0.5}
    grid = {"canvas": 24, "n_dirs": 100, "bytes_per_model": 7200, "top1_median_deg": 9.0, "best50_median_deg": 3.0}
    grid |= {"best50_p90_deg": 6.0, "render_s_per_model": 0.5}
    scale = {"models": 500, "rows": 50000, "views": 13, "query_s_min": 1.0, "query_s_median": 1.2, "index_bytes_per_model": 7000.0}
    scale |= {"consolidate_s": 3.0, "replicate_s": 9.0}
    build = {"models": 60, "build_s": 120.0, "anchor_ms": 1500.0, "workers": 2, "shard_bytes": 7200.0, "distractors": 50}
    text = write_report([scene], [grid], scale, build, True, machine, out_dir=tmp_path)
    assert "2000 ms a step" in text and machine.cpu in text and machine.load in text
    assert "| 0.900 | no | 4.0 | 2.0x | 5.0 |" in text
    assert "| 6.0 | 0.50 | 0.25x |" in text
    assert "1.20 s median (0.60x the anchor)" in text and "3.0 s (1.5x)" in text
    assert "built in 120 s (80.0x the anchor read in the run that built it" in text  # its own reading, not this run's
    old = write_report([scene], [], None, build | {"anchor_ms": None}, False, machine, name="r.md", out_dir=tmp_path)
    assert "built in 120 s (- the anchor" in old
    assert (tmp_path / "registration_quick.md").exists() and (tmp_path / "registration_grid.png").exists()

"""The rig-scenes registration tables: each cached run's time over the anchor read in the invocation that timed it."""

from __future__ import annotations

from benchmarks._common import MachineReading
from benchmarks.bench_registration_rig_scenes import write_known, write_table

MACHINE = MachineReading(2000.0, "AMD EPYC, 2 cores, AVX2 (no AVX-512), no native bfloat16", "load average 1.5 on 2 cores")


def scale_row(scene: str, seconds: float, anchor_ms: float | None) -> dict:
    row = {"scene": scene, "k": 1.0, "model": scene, "right_model": True, "add_s_pct": 1.0, "surface_pct": 1.0}
    row |= {"scale_ratio": 1.0, "part_vs_cad": None, "iou": 0.9, "near_tie": False, "decided_by": "", "model_ties": []}
    return row | {"seconds": seconds, "ok": True} | ({"anchor_ms": anchor_ms} if anchor_ms else {})


def test_scale_table_pairs_each_run_with_its_own_reading_and_marks_older_runs(tmp_path):
    rows = [scale_row("a", 30.0, 1000.0), scale_row("b", 30.0, 3000.0), scale_row("c", 50.0, None)]
    write_table(rows, MACHINE, tmp_path / "t.md")
    text = (tmp_path / "t.md").read_text()
    assert "2000 ms a step" in text and MACHINE.cpu in text
    assert "| 30.0 | 30.0x | yes |" in text and "| 30.0 | 10.0x | yes |" in text and "| 50.0 | - | yes |" in text
    assert text.rstrip().endswith("| 30.0 | 20.0x |")  # median over the runs that read an anchor: 30x and 10x


def test_known_table_states_wall_and_cpu_ratios(tmp_path):
    rows = [
        {"scene": "a", "trial": t, "seconds": s, "cpu_seconds": s / 2, "add_s_pct": 0.5, "load": 1.0, "anchor_ms": 1000.0}
        for t, s in enumerate((1.0, 2.0, 3.0))
    ]
    write_known(rows, MACHINE, tmp_path / "k.md")
    text = (tmp_path / "k.md").read_text()
    assert "| a | 3 | 2.000 (2.0x) | 3.000 (3.0x) | 1.000 (1.0x) |" in text

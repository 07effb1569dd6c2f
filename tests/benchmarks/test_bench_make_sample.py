"""The sample's summary table: the synthesis time beside its ratio to the anchor read in the same run."""

from __future__ import annotations

from benchmarks._common import MachineReading
from benchmarks.bench_make_sample import OBJECT, summary_table


def test_the_synthesis_time_carries_its_ratio_to_the_anchor_under_the_reading():
    machine = MachineReading(1500.0, "AMD EPYC, 2 cores, AVX2 (no AVX-512), no native bfloat16", "load average 0.7 on 2 cores")
    text = summary_table({"synth_s": 45.0, "views": 9, "heldout": 36}, 12_340_000, machine)
    header, _, table = text.partition("\n\n")
    assert "1500 ms a step" in header and machine.cpu in header and machine.load in header
    assert table.splitlines()[0].split(" | ")[3:5] == ["synth wall (s)", "x anchor"]
    assert table.splitlines()[-1] == f"| {OBJECT} | 9 | 36 | 45.0 | 30.0x | 12.34 |"

"""The physics demo's report: collision and wall times beside their ratio to the run's anchor reading."""

from __future__ import annotations

from types import SimpleNamespace

from benchmarks._common import MachineReading
from benchmarks.bench_simulation_demo import collision_table, wall_time_line

MACHINE = MachineReading(2000.0, "AMD EPYC, 2 cores, AVX2 (no AVX-512), no native bfloat16", "load average 1.5 on 2 cores")


def test_collision_seconds_carry_their_ratio():
    collision = SimpleNamespace(kind="coacd", hull_count=12, primitives=[], volume_error=0.04, hausdorff=0.002, seconds=300.0)
    body = SimpleNamespace(asset=SimpleNamespace(name="clamp", mass=SimpleNamespace(mass=0.1)), collision=collision)
    lines = collision_table({"twin": [body]}, MACHINE)
    assert lines[0].endswith("| collision s | x anchor |")
    assert lines[-1] == "| clamp | twin | 0.1000 | coacd | 12 | +4.0% | 2.00 | 300 | 150x |"


def test_every_wall_time_carries_its_ratio():
    line = wall_time_line({"prep_twin": 20.0, "prep_true": 10.0, "sim_twin": 1.0, "sim_true": 0.5, "render": 4.0}, 18, 40000, MACHINE)
    assert "twin bodies 20 s (10.0x;" in line and "true bodies 10 s (5.0x)" in line
    assert "simulation 1.0 s (0.50x, twin) / 0.5 s (0.25x, true)" in line and "renders 4 s (2.0x) for 18 frames (40000 splats)" in line

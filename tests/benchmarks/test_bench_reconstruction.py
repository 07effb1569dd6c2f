"""The reconstruction benchmark's markdown: sweep times against the run's anchor reading, each object's total
against the reading taken before its twin trained, and none for a reused twin."""

from __future__ import annotations

from benchmarks._common import MachineReading
from benchmarks.bench_reconstruction import write


def object_row(name: str, wall_s: float, anchor_ms: float | None) -> dict:
    row = {"object": name, "pose_mode": "rig", "splats": 20000, "iters": {"pose": 1, "deform": 2, "photo": 3}}
    row |= {"wall_s": wall_s, "anchor_ms": anchor_ms, "register_s": 5.0, "pose_s": 10.0, "deform_s": 10.0, "photo_s": 20.0}
    row |= {"fgpsnr": 20.0, "iou": 0.9, "fgpsnr_refined": 21.0, "iou_refined": 0.95, "rot_init": 1.0, "rot": 0.5}
    row |= {"ctr_init": 1.0, "ctr": 0.5, "rot_raw": 1.0, "ctr_raw": 1.0, "symmetry": "none", "ambiguity": "no", "load": 1.0}
    return row


def test_sweeps_and_objects_carry_their_ratio_to_the_anchor(tmp_path):
    machine = MachineReading(2000.0, "AMD EPYC, 2 cores, AVX2 (no AVX-512), no native bfloat16", "load average 1.5 on 2 cores")
    fields = [{"config": "cpu", "evals": 2048, "ms_per_step": 70.0, "rms_mm": 0.2, "residual_pct": 24.0}]
    batching = [{"views_per_iter": 3, "s_per_iter": 0.3, "s_per_view": 0.1}]
    objects = [object_row("050_medium_clamp", 60.0, 1500.0), object_row("011_banana", 80.0, None)]
    md = tmp_path / "reconstruction.md"
    write(fields, batching, objects, 1, machine, md)
    text = md.read_text()
    assert "2000 ms a step" in text and machine.cpu in text and machine.load in text
    assert "| cpu | 2048 | 70.0 | 0.035x | 0.200 | 24.0 |" in text
    assert "| 3 | 0.300 (0.15x) | 0.100 (0.05x) |" in text
    assert "| 60 | 40.0x | 1500 | 5 |" in text  # the object's own reading, not the sweeps'
    assert "| 80 | - | - | 5 |" in text  # a reused twin was timed in an earlier run: no ratio
    assert md.with_suffix(".png").exists()

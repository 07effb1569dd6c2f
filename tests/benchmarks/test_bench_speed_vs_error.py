"""The speed-vs-error report: a row's train time beside the median of its runs' ratios to the anchor each read."""

from __future__ import annotations

from argparse import Namespace

from benchmarks.bench_speed_vs_error import write_report


def doc(scene: str, train_s: float, anchor_ms: float | None) -> dict:
    mean = {"psnr": 20.0, "ssim": 0.8, "lpips": 0.2, "mpsnr": 21.0, "mlpips": 0.1, "fgpsnr": 18.0, "iou": 0.9}
    out = {"run": {"scene": scene, "method": "full", "preset": "cpu", "views": "all"}, "train_views": list(range(9))}
    out |= {"train_wall_s": train_s, "num_splats": 20000, "mean": mean, "mean_refined": None, "registration": {}}
    return out | ({"anchor_ms": anchor_ms} if anchor_ms else {})


def test_rows_state_the_median_ratio_and_the_header_the_readings(tmp_path):
    args = Namespace(quick=True, heldout_views=4, refine_steps=0, out=tmp_path / "sve.md")
    docs = [doc("00_clamp", 40.0, 2000.0), doc("01_scissors", 60.0, 1500.0), doc("02_banana", 90.0, None)]
    text = write_report(docs, args, 0.0)
    assert "| full | cpu | all | 3 | 63 | 30.0x | 20000 |" in text  # 20x and 40x; the run without a reading left out
    assert "readings 1500-2000 ms" in text and "AVX" in text and "load average" in text
    assert (tmp_path / "sve.md").read_text() == text
    assert (tmp_path / "sve_time.png").exists() and (tmp_path / "sve_views.png").exists() and "(sve_time.png)" in text

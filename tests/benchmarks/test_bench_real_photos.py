"""The real-photos summary row: each fold's train time over the anchor it read, a cached fold without one left out."""

from __future__ import annotations

from benchmarks.bench_real_photos import set_row


def test_a_set_row_states_the_median_ratio_of_the_folds_that_read_an_anchor():
    scores = {"psnr": 20.0, "ssim": 0.8, "lpips": 0.2, "iou": 0.9}
    folds = [
        {"train_s": 100.0, "anchor_ms": 2000.0, "mean": scores, "mean_refined": scores},
        {"train_s": 120.0, "anchor_ms": 2000.0, "mean": scores, "mean_refined": scores},
        {"train_s": 300.0, "mean": scores, "mean_refined": None},  # cached before the anchor was recorded
    ]
    cells = [c.strip() for c in set_row("espresso", folds, 8).strip("|").split("|")]
    assert cells[:5] == ["espresso", "3/8", "173", "55.0x", "2000"]
    assert cells[5:] == ["20.00", "0.800", "0.200", "20.00", "0.900"]
    old = [c.strip() for c in set_row("car", folds[2:], 8).strip("|").split("|")]
    assert old[3:5] == ["-", "-"]

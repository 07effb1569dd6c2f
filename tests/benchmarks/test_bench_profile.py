"""The profile's bucketing (`benchmarks.bench_profile.attribute`) on a synthetic event tree."""

from __future__ import annotations

import pytest

from benchmarks.bench_profile import BACKWARD_NODE, ITERATION, IterationMarks, Span, attribute, steady_cores


def _iteration(t0: float) -> list[Span]:
    """One iteration starting at t0: a labelled rasterizer forward (projection inside it), an SSIM
    forward, the backward of both, an Adam step and unlabelled glue; parents index this list."""
    return [
        Span(ITERATION, t0, t0 + 100, None),  # 0: 10 µs of its own
        Span("cs:rasterize", t0 + 0, t0 + 30, 0),  # 1: 5 own
        Span("cs:projection", t0 + 0, t0 + 10, 1),  # 2
        Span("_ProjectGaussians", t0 + 0, t0 + 10, 2, seq=7),  # 3: 10 projection
        Span("_RasterizeToPixels", t0 + 10, t0 + 25, 1, seq=8),  # 4: 15 compositing
        Span("cs:ssim", t0 + 30, t0 + 40, 0),  # 5: 2 own
        Span("aten::conv2d", t0 + 32, t0 + 40, 5, seq=9),  # 6: 8 ssim
        Span("cs:backward", t0 + 40, t0 + 80, 0),  # 7: 4 glue
        Span(BACKWARD_NODE + "ConvolutionBackward0", t0 + 40, t0 + 52, 7, seq=9),  # 8: 1 glue
        Span("ConvolutionBackward0", t0 + 41, t0 + 52, 8, seq=9),  # 9: 11 ssim
        Span(BACKWARD_NODE + "_RasterizeToPixelsBackward", t0 + 52, t0 + 70, 7, seq=8),  # 10: 1 glue
        Span("_RasterizeToPixelsBackward", t0 + 53, t0 + 70, 10, seq=8),  # 11: 17 raster bwd
        Span(BACKWARD_NODE + "torch::autograd::AccumulateGrad", t0 + 70, t0 + 76, 7),  # 12: 6 glue
        Span("cs:optimizer", t0 + 80, t0 + 90, 0),  # 13: 10 optimizer
    ]


def test_attribute_buckets_self_time_by_label_and_backward_by_forward_label():
    spans = _iteration(0.0)
    second = [Span(s.name, s.start_us, s.end_us, None if s.parent is None else s.parent + len(spans), s.seq) for s in _iteration(1000.0)]
    outside = [Span("aten::add", 2000.0, 2050.0, None, seq=3)]
    per_iter = attribute(spans + second + outside)
    assert len(per_iter) == 2
    first = per_iter[0]
    assert first == pytest.approx(
        {
            "wall": 100,
            "else": 10,
            "raster_fwd_other": 5,
            "raster_fwd_projection": 10,
            "raster_fwd_compositing": 15,
            "ssim": 2 + 8 + 11,
            "glue": 4 + 1 + 1 + 6,
            "raster_bwd": 17,
            "optimizer": 10,
        }
    )
    # Every microsecond of the iteration lands in exactly one bucket.
    assert sum(v for k, v in first.items() if k != "wall") == pytest.approx(first["wall"])
    assert per_iter[1] == pytest.approx(first)


def test_backward_node_without_a_labelled_forward_is_everything_else():
    spans = [
        Span(ITERATION, 0, 50, None),
        Span("aten::mul", 0, 10, 0, seq=4),
        Span(BACKWARD_NODE + "MulBackward0", 10, 30, 0, seq=4),
        Span("MulBackward0", 10, 30, 2, seq=4),
    ]
    assert attribute(spans)[0] == pytest.approx({"wall": 50, "else": 20 + 10 + 20, "glue": 0})


def test_cores_busy_is_cpu_over_wall_per_stage_without_its_warm_up():
    marks = IterationMarks(profiled=False)
    # (stage, iteration, wall s, CPU s) at each progress call, made as each iteration ends: the interval up to a
    # call is that call's iteration.
    calls = [
        ("pose", 1, 0.0, 0.0),
        ("pose", 2, 1.0, 1.0),
        ("pose", 3, 2.0, 2.0),
        ("pose", 4, 3.0, 4.0),
        ("photo", 1, 4.0, 5.5),
        ("photo", 2, 5.0, 7.5),
        ("photo", 3, 6.0, 9.5),
        ("photo", 4, 8.0, 12.5),
    ]
    marks.calls = [(s, i) for s, i, _, _ in calls]
    marks.times = [t for *_, t, _ in calls]
    marks.cpu_times = [c for *_, c in calls]
    # Iterations 1-2 of each stage are warm-up. Pose keeps 3 (1 CPU s in 1 s) and 4 (2 in 1); photo keeps 3 (2 in 1)
    # and 4 (3 in 2).
    assert steady_cores(marks) == pytest.approx({"pose": 3 / 2, "photo": 5 / 3})


def test_every_labelled_engine_function_exists_and_is_restored():
    """The labels name engine functions by attribute: one renamed or removed in the engine breaks the profile before it
    runs (the checkpoint writer moved to the pipeline's `FileCheckpoint` once and the benchmark stopped at its start)."""
    import reconstruction.pipeline as pipeline
    import reconstruction.train as train
    from benchmarks.bench_profile import labels

    before = (train.rasterize, pipeline.FileCheckpoint.save)
    with labels():
        assert train.rasterize is not before[0]
        assert pipeline.FileCheckpoint.save is not before[1]
    assert (train.rasterize, pipeline.FileCheckpoint.save) == before

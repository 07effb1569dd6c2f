"""Where each millisecond of a training iteration goes (issue 20): the production training loop,
profiled per stage and per bucket.

    python -m benchmarks.bench_profile [--preset cpu|preview] [--capture DIR] [--library DIR] [--iters N] [--out FILE]

`reconstruct` runs exactly as in production on the bundled sample (`sample/train` against a library
built from `sample/library_meshes`), or on `--capture` (a capture, or a rig scene holding `train/`;
its library from `--library`, else built from `shared/data/rig_scenes/library`). It runs twice: once
as production runs it (the preset unchanged: wall time per stage, iterations, median wall per
iteration, cores busy per stage from the process's CPU time; numba's kernels loaded), then under
`torch.profiler` (CPU activity, no shapes) with each stage capped at `--iters` iterations and the plateau stop off so every stage runs them all. The engine is not changed: the benchmark wraps a few
engine functions in `record_function` labels for the run (projection, binning, the losses, the
deformation field, the pose correction, the backward call) and a label per iteration opened and
closed by the progress callback. The numba kernels run on the rasterizer's worker threads while the
main thread waits inside the enclosing label or autograd Function (`_ProjectGaussians`,
`_RasterizeToPixels`, `_EvalSH`), so main-thread self time attributes them. A backward node is
charged to the label that enclosed the forward op that made it (the profiler's sequence numbers);
the engine's own time between nodes is "autograd engine glue". The first `WARMUP` iterations of
each stage (stage set-up, lazy optimizer state) are left out.

Writes (appends the preset's section to) benchmarks/results/profile.md.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import tempfile
import time
from collections import defaultdict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from benchmarks._common import REPO, RESULTS, SHARED, cpu_line, load_line
from reconstruction.render.anchor import anchor_ms

ITERATION = "cs:iteration"
WARMUP = 2
# Rows of the table, in order: key -> label.
BUCKETS = {
    "raster_fwd_projection": "rasterizer forward: projection + SH colours",
    "raster_fwd_binning": "rasterizer forward: binning + per-tile sort",
    "raster_fwd_compositing": "rasterizer forward: compositing",
    "raster_fwd_other": "rasterizer forward: casts, checks",
    "raster_bwd": "rasterizer backward",
    "ssim": "SSIM + L1 sums (forward + backward)",
    "sh_loss": "SH-neighbour loss (forward + backward)",
    "consistency": "photo-consistency, Stage I (forward + backward)",
    "field": "deformation MLP (forward + backward)",
    "pose": "pose correction (forward + backward)",
    "optimizer": "Adam / optimizer (zero_grad, step, finite check, clamp)",
    "glue": "autograd engine glue",
    "checkpoint": "checkpoint write",
    "else": "everything else (mask losses, crops, activations, Python)",
}
RASTERIZER = ("raster_fwd_projection", "raster_fwd_binning", "raster_fwd_compositing", "raster_fwd_other", "raster_bwd")
# Profiler event names (the benchmark's labels, autograd Functions) -> bucket.
LABELS = {
    "cs:rasterize": "raster_fwd_other",
    "cs:projection": "raster_fwd_projection",
    "cs:sh_colours": "raster_fwd_projection",
    "cs:binning": "raster_fwd_binning",
    "_RasterizeToPixels": "raster_fwd_compositing",
    "cs:ssim": "ssim",
    "cs:sh_loss": "sh_loss",
    "cs:consistency": "consistency",
    "cs:field": "field",
    "cs:pose": "pose",
    "cs:optimizer": "optimizer",
    "cs:backward": "glue",
    "cs:checkpoint": "checkpoint",
}
BACKWARD_NODE = "autograd::engine::evaluate_function: "


@dataclass(frozen=True)
class Span:
    """One profiler event on one thread: `parent` indexes the enclosing span (None at the top), `seq`
    is the autograd sequence number (-1 without one), times in microseconds."""

    name: str
    start_us: float
    end_us: float
    parent: int | None
    seq: int = -1


def attribute(spans: Sequence[Span]) -> list[dict[str, float]]:
    """Self time (µs) per bucket of every `ITERATION` span, in the order they start, with its wall
    time under "wall". Forward time goes to the innermost `LABELS` span enclosing it; time inside a
    backward node (`BACKWARD_NODE` span) to the label of the forward op with the node's sequence
    number (rasterizer labels to "raster_bwd"), the node's own self time and AccumulateGrad to "glue";
    what no label encloses to "else". Spans outside every iteration are ignored."""
    children_us = [0.0] * len(spans)
    for s in spans:
        if s.parent is not None:
            children_us[s.parent] += s.end_us - s.start_us

    def ancestry(i: int) -> Iterator[int]:
        j: int | None = i
        while j is not None:
            yield j
            j = spans[j].parent

    def context(i: int) -> tuple[int | None, int | None, str | None]:
        """(enclosing iteration, innermost enclosing backward node, innermost label) of span i (itself included)."""
        it = node = None
        label = None
        for j in ancestry(i):
            name = spans[j].name
            if name == ITERATION and it is None:
                it = j
            elif name.startswith(BACKWARD_NODE) and node is None:
                node = j
            elif name in LABELS and label is None and node is None:
                label = LABELS[name]
        return it, node, label

    contexts = [context(i) for i in range(len(spans))]
    forward_bucket: dict[int, str] = {}
    for i, s in enumerate(spans):
        it, node, label = contexts[i]
        if s.seq >= 0 and node is None and not s.name.startswith(BACKWARD_NODE) and s.seq not in forward_bucket:
            forward_bucket[s.seq] = label or "else"
    iterations = sorted((s.start_us, i) for i, s in enumerate(spans) if s.name == ITERATION)
    out = {i: defaultdict(float, wall=spans[i].end_us - spans[i].start_us) for _, i in iterations}
    for i, s in enumerate(spans):
        it, node, label = contexts[i]
        if it is None:
            continue
        self_us = s.end_us - s.start_us - children_us[i]
        if s.name == ITERATION:
            bucket = "else"
        elif node is None:
            bucket = label or "else"
        elif node == i or "AccumulateGrad" in spans[node].name:
            bucket = "glue"
        else:
            fwd = forward_bucket.get(spans[node].seq, "else")
            bucket = "raster_bwd" if fwd in RASTERIZER else fwd
        out[it][bucket] += self_us
    return [dict(out[i]) for _, i in iterations]


def spans_of(events, thread: int) -> list[Span]:
    """`Span`s of torch profiler `events` (FunctionEvents) on `thread`."""
    mine = [e for e in events if e.thread == thread]
    index = {e.id: k for k, e in enumerate(mine)}
    return [
        Span(e.name, e.time_range.start, e.time_range.end, index.get(e.cpu_parent.id) if e.cpu_parent is not None else None, e.sequence_nr)
        for e in mine
    ]


def _labelled(fn, label: str):
    def wrapper(*args, **kwargs):
        with torch.profiler.record_function(label):
            return fn(*args, **kwargs)

    return wrapper


@contextlib.contextmanager
def labels() -> Iterator[None]:
    """The engine functions wrapped in their `record_function` labels for the duration (module
    attributes patched and restored; the code is unchanged)."""
    import reconstruction.adam as adam
    import reconstruction.deformation as deformation
    import reconstruction.losses as losses
    import reconstruction.pipeline as pipeline
    import reconstruction.render.rasterization as rasterization
    import reconstruction.train as train

    targets = [
        (train, "rasterize", "cs:rasterize"),
        (rasterization, "project_gaussians", "cs:projection"),
        (rasterization, "sh_colors", "cs:sh_colours"),
        (rasterization, "bin_gaussians", "cs:binning"),
        (losses, "ssim_map", "cs:ssim"),
        (losses, "dssim_l1_sums", "cs:ssim"),
        (train, "sh_neighbour_loss", "cs:sh_loss"),
        (train, "sample_colors", "cs:consistency"),
        (train, "consistency_loss", "cs:consistency"),
        (deformation.DeformationField, "forward", "cs:field"),
        (train.SplatModel, "viewmats", "cs:pose"),
        (train.SplatModel, "clamp_", "cs:optimizer"),
        (train, "_grads_finite", "cs:optimizer"),
        (adam.Adam, "step", "cs:optimizer"),
        (adam.Adam, "zero_grad", "cs:optimizer"),
        (pipeline.FileCheckpoint, "save", "cs:checkpoint"),
        (torch.autograd, "backward", "cs:backward"),
    ]
    saved = [(owner, name, getattr(owner, name)) for owner, name, _ in targets]
    try:
        for owner, name, label in targets:
            setattr(owner, name, _labelled(getattr(owner, name), label))
        yield
    finally:
        for owner, name, fn in saved:
            setattr(owner, name, fn)


class IterationMarks:
    """Progress callback: the end time of every iteration and, profiled, an `ITERATION` label closed
    and reopened there, so label k and the interval between calls k and k+1 both span iteration
    `stages[k]`; the first iteration has neither."""

    def __init__(self, profiled: bool):
        self.profiled = profiled
        self.calls: list[tuple[str, int]] = []
        self.times: list[float] = []
        self.cpu_times: list[float] = []  # the process's CPU seconds (all threads) at each call
        self._open = None

    @property
    def stages(self) -> list[tuple[str, int]]:
        return self.calls[1:]

    def __call__(self, stage: str, it: int, _cap: int, _loss: float) -> None:
        self.times.append(time.perf_counter())
        self.cpu_times.append(time.process_time())
        self.calls.append((stage, it))
        if self._open is not None:
            self._open.__exit__(None, None, None)
        if self.profiled:
            self._open = torch.profiler.record_function(ITERATION)
            self._open.__enter__()

    def close(self) -> None:
        if self._open is not None:
            self._open.__exit__(None, None, None)
            self._open = None


def steady_wall_ms(marks: IterationMarks) -> dict[str, float]:
    """Median wall ms per iteration of each stage from a run's progress times, warm-up left out."""
    per: dict[str, list[float]] = defaultdict(list)
    for (stage, it), t0, t1 in zip(marks.stages, marks.times, marks.times[1:]):
        if it > WARMUP:
            per[stage].append(1000 * (t1 - t0))
    return {s: float(np.median(v)) for s, v in per.items()}


def steady_cores(marks: IterationMarks) -> dict[str, float]:
    """Cores busy in each stage's steady iterations (warm-up left out): the process's CPU seconds over wall
    seconds, 2.0 when both of two cores worked throughout."""
    cpu: dict[str, float] = defaultdict(float)
    wall: dict[str, float] = defaultdict(float)
    steps = zip(marks.stages, zip(marks.times, marks.times[1:]), zip(marks.cpu_times, marks.cpu_times[1:]))
    for (stage, it), (t0, t1), (c0, c1) in steps:
        if it > WARMUP:
            cpu[stage] += c1 - c0
            wall[stage] += t1 - t0
    return {s: cpu[s] / wall[s] for s in wall if wall[s] > 0}


def run(capture: Path, library: Path, preset: str, iters: int | None, work: Path, profiled: bool):
    """One `reconstruct`; with `iters`, every stage capped at `iters` and the plateau stop off.
    Returns (reconstruction, marks, profiler or None)."""
    from torch.profiler import ProfilerActivity, profile

    from reconstruction.pipeline import reconstruct_capture

    marks = IterationMarks(profiled)
    overrides = None if iters is None else {"iters_pose": iters, "iters_deform": iters, "iters_photo": iters, "plateau": False}
    out = work / ("twin-profiled" if profiled else "twin-plain")
    shutil.rmtree(out, ignore_errors=True)
    prof = profile(activities=[ProfilerActivity.CPU], record_shapes=False) if profiled else None
    with labels() if profiled else contextlib.nullcontext(), prof if prof is not None else contextlib.nullcontext():
        try:
            rec = reconstruct_capture(capture, library, out, preset=preset, overrides=overrides, progress=marks, overwrite=True)
        finally:
            marks.close()
    return rec, marks, prof


def table(
    per_iter: list[dict[str, float]],
    stages: list[tuple[str, int]],
    plain_ms: dict[str, float],
    stage_wall_s: dict[str, float],
    iterations: dict[str, int],
    cores: dict[str, float] | None = None,
) -> tuple[str, dict[str, int]]:
    """Markdown table: ms per iteration and % of the profiled iteration per bucket and stage (median
    over the stage's steady iterations), plus the rasterizer's share, the stage walls and, with `cores`
    (`steady_cores` of the production run), how many cores each stage kept busy."""
    by_stage: dict[str, list[dict[str, float]]] = defaultdict(list)
    for rec, (stage, it) in zip(per_iter, stages):
        if it > WARMUP:
            by_stage[stage].append(rec)
    order = [s for s in ("pose", "deform", "photo") if by_stage[s]]
    mean = {s: {k: float(np.mean([r.get(k, 0.0) for r in by_stage[s]])) / 1000 for k in [*BUCKETS, "wall"]} for s in order}
    names = {"pose": "Stage I pose", "deform": "Stage I pose+deformation", "photo": "Stage II photometric"}
    lines = ["| where (ms per iteration, % of it) | " + " | ".join(names[s] for s in order) + " |", "|---|" + "---|" * len(order)]
    for key, label in BUCKETS.items():
        cells = [f"{mean[s][key]:.1f} ({100 * mean[s][key] / mean[s]['wall']:.0f} %)" for s in order]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines.append("| **iteration, profiled** | " + " | ".join(f"**{mean[s]['wall']:.1f}**" for s in order) + " |")
    spread = {s: np.percentile([r["wall"] for r in by_stage[s]], [10, 90]) / 1000 for s in order}
    lines.append(
        "| iteration, profiled: 10th-90th percentile | " + " | ".join(f"{spread[s][0]:.1f}-{spread[s][1]:.1f}" for s in order) + " |"
    )
    lines.append("| iteration, production run (median) | " + " | ".join(f"{plain_ms.get(s, float('nan')):.1f}" for s in order) + " |")
    outside = [100 * (1 - sum(mean[s][k] for k in RASTERIZER) / mean[s]["wall"]) for s in order]
    lines.append("| **outside the rasterizer** | " + " | ".join(f"**{o:.0f} %**" for o in outside) + " |")
    if cores is not None:
        lines.append(
            f"| cores busy, production run (CPU s per wall s, of {os.cpu_count()}) | "
            + " | ".join(f"{cores[s]:.2f}" if s in cores else "-" for s in order)
            + " |"
        )
    lines.append(
        "| stage wall, production run (s; iterations) | "
        + " | ".join(f"{stage_wall_s.get(s, 0):.1f} ({iterations.get(s, 0)})" for s in order)
        + " |"
    )
    # The whole training: each stage's profiled iteration weighted by the production run's iteration count.
    total = sum(iterations.get(s, 0) * mean[s]["wall"] for s in order)
    raster = sum(iterations.get(s, 0) * sum(mean[s][k] for k in RASTERIZER) for s in order)
    if total > 0:
        lines += [
            "",
            f"Outside the rasterizer over the whole training (stages weighted by the production run's iterations): "
            f"**{100 * (1 - raster / total):.0f} %**.",
        ]
    return "\n".join(lines), {s: len(by_stage[s]) for s in order}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="cpu", choices=["cpu", "preview"])
    ap.add_argument("--capture", type=Path, default=None, help="a capture, or a rig scene holding train/ (default: the bundled sample)")
    ap.add_argument(
        "--library", type=Path, default=None, help="a built library for --capture (default: built from shared rig_scenes/library)"
    )
    ap.add_argument("--iters", type=int, default=30, help="iterations per stage (each stage runs exactly this many)")
    ap.add_argument("--work", type=Path, default=None, help="scratch directory (default: a temporary one)")
    ap.add_argument("--out", type=Path, default=RESULTS / "profile.md", help="markdown file the section is appended to")
    args = ap.parse_args()
    if args.iters <= WARMUP:
        raise SystemExit(f"--iters must exceed the {WARMUP} warm-up iterations per stage")
    from reconstruction.library import build_library

    work = args.work or Path(tempfile.mkdtemp(prefix="cadsplat-profile-"))
    work.mkdir(parents=True, exist_ok=True)
    if args.capture is None:
        capture, meshes, scene = REPO / "sample" / "train", REPO / "sample" / "library_meshes", "bundled sample"
    else:
        capture = args.capture / "train" if (args.capture / "train").is_dir() else args.capture
        meshes, scene = SHARED / "rig_scenes" / "library", str(args.capture)
        if not capture.is_dir():
            raise SystemExit(f"{capture} is not here: nothing to profile")
    library = args.library or work / "library"
    if not (library / "library.json").exists():
        if not meshes.is_dir():
            raise SystemExit(f"{meshes} is not here (shared data absent): give --library for this capture")
        build_library(meshes, library, progress=False, log=lambda _m: None)
    from reconstruction.warmup import compile_kernels

    compile_kernels()  # as `make env` does: no compile in the production run's registration or first iterations
    load = os.getloadavg()
    machine = anchor_ms()
    rec, marks, _ = run(capture, library, args.preset, None, work, profiled=False)
    plain_ms = steady_wall_ms(marks)
    cores = steady_cores(marks)
    stage_wall = dict(rec.train.timings_s)
    print(f"production run: {stage_wall} s, {rec.train.iterations} iterations, median ms/iter {plain_ms}, cores busy {cores}", flush=True)
    _, marks, prof = run(capture, library, args.preset, args.iters, work, profiled=True)
    events = prof.events()
    spans = spans_of(events, thread=next(e.thread for e in events if e.name == ITERATION))
    text, counts = table(attribute(spans), marks.stages, plain_ms, stage_wall, rec.train.iterations, cores)
    cmd = "python -m benchmarks.bench_profile " + " ".join(
        f"--{k} {v}" for k, v in (("preset", args.preset), ("capture", args.capture), ("iters", args.iters)) if v is not None
    )
    section = "\n".join(
        [
            f"## `{args.preset}` preset, {scene}",
            "",
            f"`{cmd}` — {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; load average {load[0]:.1f} / {load[1]:.1f} / "
            f"{load[2]:.1f} (1/5/15 min) on {os.cpu_count()} cores at the start; CPU {cpu_line()}; the anchor {machine:.0f} ms a step "
            f"(`reconstruction.render.anchor`), the production run {1000 * rec.twin.timings_s['total'] / machine:.1f}x the anchor; the run "
            f"then keeps both cores busy ({load_line()} at its end); "
            f"torch threads {torch.get_num_threads()}; {rec.twin.num_splats} splats; production run {rec.twin.timings_s['total']:.1f} s "
            f"end to end; profiled run: each stage capped at {args.iters} iterations, plateau stop off; profiled iterations "
            f"per stage (first {WARMUP} left out): " + ", ".join(f"{s} {n}" for s, n in counts.items()) + ".",
            "",
            "Bucket times are the profiled run's means (main-thread self time; the rasterizer's numba kernels run on its "
            "worker threads while the main thread waits inside the rasterizer); the profiler adds its own overhead (compare "
            "the profiled iteration with the production run's). Checkpoints are written every `checkpoint_every` iterations "
            "(50 in `cpu` and `preview`): with fewer capped iterations the checkpoint row stays 0.",
            "",
            text,
            "",
        ]
    )
    print(section, flush=True)
    header = (
        "# Where an iteration's time goes (`python -m benchmarks.bench_profile`)\n\n"
        "Issue 20's measuring stick: the production training loop per stage, by bucket. Method: the module "
        "docstring of benchmarks/bench_profile.py.\n\n"
    )
    previous = args.out.read_text() if args.out.exists() else header
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(previous.rstrip("\n") + "\n\n" + section)
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()

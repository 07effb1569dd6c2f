"""Acquisition benchmark: trigger-to-committed latency and sustained captures/s with 4, 8 and 13 cameras at 640x480.

Frame sources (cheap, so the numbers measure acquisition + validation + PNG + fsync + verify):
- `pattern`: rig/synthetic_driver.PatternCamera (smooth gradient + bar; compresses well),
- `pattern+noise`: the same with sensor-like noise (sigma 3 grey levels; PNGs as large as a real camera's).
Triggers are software events fired back to back (the next one as soon as the previous capture is
committed), so captures/s is the sustained rate of the store. The synthetic MuJoCo rig's render
cost per trigger is reported separately (`--render`). Both tables state the speed anchor's step read at the
start of the run (`benchmarks._common.machine_reading`) and give each time's ratio to it (`x anchor`: the
median latency, the render seconds per trigger).

    python -m benchmarks.bench_acquisition [--captures 20] [--render] [--out FILE.md]

Prints a markdown table and writes benchmarks/results/acquisition.md (or --out) and a plot beside it.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._common import RESULTS, machine_reading
from rig.acquisition import Acquisition, Thresholds, agree_photometry
from rig.camera import CameraSettings
from rig.store import CaptureStore
from rig.synthetic_driver import PatternCamera
from rig.triggers import SoftwareTrigger

W, H = 640, 480


class NoisyPatternCamera(PatternCamera):
    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self._rng = np.random.default_rng(self.index)
        self._noise = None

    def grab(self, timeout_s):
        f = super().grab(timeout_s)
        if self._noise is None:  # a few noise fields, cycled: drawing fresh noise each time would dominate the timing
            self._noise = [self._rng.normal(0, 3, f.image.shape).astype(np.int16) for _ in range(4)]
        img = np.clip(f.image.astype(np.int16) + self._noise[self._frames % 4], 0, 255).astype(np.uint8)
        return type(f)(f.camera_id, img, f.timestamp_ns, f.settings)


def run(source: str, n_cams: int, captures: int, root: Path) -> dict:
    cls = NoisyPatternCamera if source == "pattern+noise" else PatternCamera
    cams = [cls(f"cam{i:02d}", index=i, n=n_cams, width=W, height=H) for i in range(n_cams)]
    for c in cams:
        c.open()
    store = CaptureStore(root, min_free_bytes=0)
    acq = Acquisition(
        cams, store, thresholds=Thresholds(sync_tolerance_ns=50_000_000), settings=agree_photometry(cams, CameraSettings(W, H))
    )
    trig = SoftwareTrigger()
    acq.handle(trig.fire())  # warm-up (thread pool, first PNG encode)
    lat = []
    t0 = time.perf_counter()
    for _ in range(captures):
        out = acq.handle(trig.fire())
        assert out.status == "committed", out.reason
        lat.append(out.latency_ns / 1e6)
    wall = time.perf_counter() - t0
    acq.close()
    size = sum(p.stat().st_size for p in (root / "captures").rglob("*") if p.is_file()) / (captures + 1)
    return {
        "source": source,
        "cameras": n_cams,
        "median_ms": float(np.median(lat)),
        "p99_ms": float(np.percentile(lat, 99)),
        "captures_per_s": captures / wall,
        "mb_per_capture": size / 1e6,
        "mb_per_s": size * captures / wall / 1e6,
    }


def render_cost(views: int, captures: int) -> float:
    from rig.assembly import sample_mesh
    from rig.synthetic_driver import SyntheticRig, procedural_part

    rig = SyntheticRig.from_mesh(sample_mesh() or procedural_part(), views, width=W, height=H)
    rig.views(0)
    t = time.perf_counter()
    for s in range(1, captures + 1):
        rig.views(s)
    rig.close()
    return (time.perf_counter() - t) / captures


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--captures", type=int, default=20)
    ap.add_argument("--render", action="store_true", help="also time the synthetic MuJoCo rig's render per trigger")
    ap.add_argument("--out", type=Path, default=RESULTS / "acquisition.md")
    args = ap.parse_args()
    machine = machine_reading()
    rows = []
    for source in ("pattern", "pattern+noise"):
        for n in (4, 8, 13):
            with tempfile.TemporaryDirectory() as d:
                rows.append(run(source, n, args.captures, Path(d)))
                print(f"  {source} {n} cams: {rows[-1]['median_ms']:.0f} ms median", file=sys.stderr)
    lines = [
        f"Acquisition at {W}x{H}, {args.captures} back-to-back software triggers per row, store on the local disk (fsync on). "
        f"{machine.header()} `x anchor` of a row: its median latency over the anchor step.",
        "",
        "| frame source | cameras | latency median (ms) | x anchor | latency p99 (ms) | captures/s | MB/capture | MB/s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['source']} | {r['cameras']} | {r['median_ms']:.0f} | {machine.x_anchor(r['median_ms'] / 1000)} | {r['p99_ms']:.0f} "
            f"| {r['captures_per_s']:.2f} | {r['mb_per_capture']:.2f} | {r['mb_per_s']:.1f} |"
        )
    if args.render:
        lines += ["", "| synthetic MuJoCo rig (render only) | cameras | s per trigger | x anchor |", "|---|---:|---:|---:|"]
        for n in (4, 8, 13):
            per_trigger = render_cost(n, 3)
            lines.append(f"| sample mesh | {n} | {per_trigger:.2f} | {machine.x_anchor(per_trigger)} |")
    table = "\n".join(lines)
    print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(table + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.5))
    for source in ("pattern", "pattern+noise"):
        rs = [r for r in rows if r["source"] == source]
        x = [r["cameras"] for r in rs]
        a.errorbar(
            x,
            [r["median_ms"] for r in rs],
            yerr=[[0] * len(rs), [r["p99_ms"] - r["median_ms"] for r in rs]],
            marker="o",
            capsize=3,
            label=source,
        )
        b.plot(x, [r["captures_per_s"] for r in rs], marker="o", label=source)
    a.set(xlabel="cameras", ylabel="trigger -> committed (ms)", title="latency (median, bar to p99)")
    b.set(xlabel="cameras", ylabel="captures / s", title="sustained rate")
    for ax in (a, b):
        ax.set_xticks([4, 8, 13])
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(args.out.with_suffix(".png"), dpi=120)


if __name__ == "__main__":
    main()

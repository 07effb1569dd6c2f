"""Synthetic rig speed: render time per view against image size (flat background vs backdrop), and
the wall time of a full `synth_dataset` (9 train + 36 held-out views). Every time is followed by its ratio to
the speed anchor's step read at the start of the run (`x anchor`; `benchmarks._common.machine_reading`, whose
ms, CPU and load head the tables).

    python -m benchmarks.bench_synthetic [--mesh PATH] [--out DIR]

Prints markdown tables; writes benchmarks/results/synthetic.md and synthetic_render.png (or into --out).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._common import REPO, RESULTS, machine_reading
from rig.synthetic import SyntheticScene, load_textured_mesh, ring_rig, synth_dataset

SIZES = [(160, 120), (320, 240), (640, 480), (1280, 960)]


def time_renders(scene: SyntheticScene, size: tuple[int, int], n: int = 8) -> float:
    """Median seconds per view (lit RGB + segmentation mask), first frame excluded."""
    radius = scene.mesh.radius / np.sin(0.85 * np.radians(45.0) * 0.75 / 2)
    cams = ring_rig(n + 1, radius=radius, elevations_deg=(25.0,), target=scene.mesh.bounds.mean(0), width=size[0], height=size[1])
    scene.render(cams[:1])
    times = []
    for cam in cams[1:]:
        t = time.perf_counter()
        scene.render([cam])
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", type=Path, default=REPO / "sample" / "object" / "050_medium_clamp.obj")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    machine = machine_reading()
    x = machine.x_anchor

    t = time.perf_counter()
    mesh = load_textured_mesh(args.mesh)
    load_s = time.perf_counter() - t
    rows = {}
    for backdrop in (False, True):
        t = time.perf_counter()
        with SyntheticScene(mesh, backdrop=backdrop) as scene:
            build_s = time.perf_counter() - t
            rows[backdrop] = (build_s, [time_renders(scene, s) for s in SIZES])

    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        synth_dataset(args.mesh, Path(tmp) / "d", views=9, heldout=36, size=(320, 240), seed=0)
        synth_s = time.perf_counter() - t

    lines = [
        f"Mesh: {args.mesh.name} ({len(mesh.faces)} faces, texture {mesh.texture.shape[1]}x{mesh.texture.shape[0]}), load {load_s:.2f} s ({x(load_s)}). "
        f"MuJoCo renderer, EGL (Mesa llvmpipe, CPU), machine shared with other jobs. {machine.header()} "
        "Each time is followed by its `x anchor` in brackets.",
        "",
        "| background | scene build (s) | " + " | ".join(f"{w}x{h} ms/view" for w, h in SIZES) + " |",
        "|---|---|" + "---|" * len(SIZES),
    ]
    for backdrop, (build_s, times) in rows.items():
        lines.append(
            f"| {'backdrop + shadows' if backdrop else 'flat'} | {build_s:.2f} ({x(build_s)}) | "
            + " | ".join(f"{1e3 * t:.0f} ({x(t)})" for t in times)
            + " |"
        )
    lines += [
        "",
        "| synth_dataset | views | wall (s) | s/view incl. backgrounds + PNG writes |",
        "|---|---|---|---|",
        f"| 320x240, flat | 9 + 36 | {synth_s:.1f} ({x(synth_s)}) | {synth_s / 45:.2f} ({x(synth_s / 45)}) |",
    ]
    text = "\n".join(lines)
    print(text)
    (args.out / "synthetic.md").write_text(text + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5))
    px = [w * h for w, h in SIZES]
    for backdrop, (_, times) in rows.items():
        ax.plot(px, np.array(times) * 1e3, "o-", label="backdrop + shadows" if backdrop else "flat background")
    ax.set_xscale("log")
    ax.set_xlabel("pixels per view")
    ax.set_ylabel("ms per view (RGB + mask)")
    ax.set_title("Synthetic rig render time")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "synthetic_render.png", dpi=120)
    return 0


if __name__ == "__main__":
    sys.exit(main())

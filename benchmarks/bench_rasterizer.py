"""CPU rasterizer speed: forward+backward ms per iteration against a tiled pure-PyTorch rasterizer.

    python -m benchmarks.bench_rasterizer [--mesh PATH] [--sizes 256 512] [--counts 10000 ...] [--no-production]

Gaussians are sampled on a real mesh (by default the speed anchor's YCB banana, `reconstruction/render/anchor.py`),
flattened along the surface normal, with the camera zoomed so the object covers ~30% of the image.
Every configuration runs in a fresh subprocess so its peak memory is its own; inside it, our
rasterizer and a tiled pure-PyTorch pipeline (projection + tile binning + per-tile torch compositing,
autograd for the backward) render the same scene, and their images are compared (the baseline is
timed in float32 and compared in float64). A second table times the `cpu` preset's batched render
(`run_production`), forward and backward apart. Both tables state each time as a ratio to the speed anchor's step
(`reconstruction.render.anchor.anchor_ms`, read before and after the rows; the mean of the two), the figure that
carries from one machine to another. Prints the markdown tables and writes them to benchmarks/results/rasterizer.md.

Subprocesses inherit the short OpenMP spin `benchmarks` sets, as the engine runs: under libgomp's
default torch's workers spin for milliseconds after every op, and on a busy 2-core machine that
spinning, not the code under test, decides the timings (see reconstruction/parallel.py). The
pure-torch baseline, thousands of small ops, runs 2-3x faster with the short spin than with workers
that sleep at once (rig_scenes.md, 2026-11-27), and the speed-up column reads lower for it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks._common import REPO, RESULTS, cpu_line
from reconstruction.parallel import openmp_wait
from reconstruction.render import rasterize
from reconstruction.render.anchor import ANCHOR_MESH, TARGET_COVERAGE, anchor_ms, diagonal_camera, torch_tiled_rasterize
from reconstruction.render.anchor import fit_focal as anchor_focal
from reconstruction.render.anchor import surface_gaussians as make_gaussians

DEFAULT_MESH = ANCHOR_MESH
# The `cpu` preset's training batch: every view in one call. The focal puts the banana on ~10% of the tiles.
PRODUCTION = {"n_cams": 10, "width": 320, "height": 240, "n": 15_000, "focal": 360.0}
# Floating-point operations per shaded (pixel, Gaussian) pair, an FMA counting as 2: forward ~60
# (offsets and quadratic form 10, exp polynomial 36, alpha and transmittance 6, colour 6), backward
# ~100 (the same exp and quadratic form, division, colour/alpha/conic/mean gradients). Pairs listed
# but not shaded are not counted, so this understates the work slightly. Only for the FLOP-bound note.
FLOPS_PER_PAIR = 160


# --------------------------------------------------------------------------- scene


def load_mesh(path: Path):
    import trimesh

    return trimesh.load(path, force="mesh"), path.name


def fit_focal(mesh, size: int) -> tuple[float, float]:
    """Focal length at which alpha > 0.5 covers ~30% of the image (returns focal, coverage)."""
    focal = anchor_focal(mesh, size)
    viewmat, K = diagonal_camera(mesh, size, focal)
    _, alphas, _ = rasterize(*make_gaussians(mesh, 20_000, seed=1).values(), viewmat, K, size, size)
    return focal, float((alphas > 0.5).float().mean())


def ring_cameras(mesh, n_cams: int, width: int, height: int, focal: float) -> tuple[torch.Tensor, torch.Tensor]:
    """n_cams cameras on a ring 35 degrees above the mesh centre, 4 bounding radii away, looking at it."""
    centre = mesh.bounds.mean(axis=0)
    radius = float(np.linalg.norm(mesh.extents)) / 2.0
    viewmats = []
    for k in range(n_cams):
        az, el = 2.0 * math.pi * k / n_cams, math.radians(35.0)
        eye = centre + 4.0 * radius * np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
        fwd = (centre - eye) / np.linalg.norm(centre - eye)
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        R = np.stack([right, np.cross(fwd, right), fwd])
        viewmat = np.eye(4)
        viewmat[:3, :3], viewmat[:3, 3] = R, -R @ eye
        viewmats.append(viewmat)
    K = np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    return torch.tensor(np.stack(viewmats), dtype=torch.float32), torch.tensor(np.stack([K] * n_cams), dtype=torch.float32)


def peak_rss_mib() -> float:
    """Peak resident set of this process so far (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def current_rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def time_iterations(step, min_seconds: float, min_iters: int, max_iters: int) -> tuple[float, float]:
    """Median wall ms and median process CPU ms (all threads) of step() over at least min_iters calls
    and min_seconds of wall time. CPU time shows the work itself when other processes share the cores."""
    wall, cpu = [], []
    start = time.perf_counter()
    while len(wall) < max_iters and (len(wall) < min_iters or time.perf_counter() - start < min_seconds):
        t, c = time.perf_counter(), time.process_time()
        step()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return 1e3 * float(np.median(wall)), 1e3 * float(np.median(cpu))


def run_one(mesh_path: Path, size: int, n: int, focal: float, torch_iters: int) -> dict:
    mesh, _ = load_mesh(mesh_path)
    g = make_gaussians(mesh, n)
    viewmat, K = diagonal_camera(mesh, size, focal)
    params = {k: v.clone().requires_grad_(True) for k, v in g.items()}
    target = torch.rand(1, size, size, 3, generator=torch.Generator().manual_seed(0))

    def ours():
        for p in params.values():
            p.grad = None
        colors, alphas, meta = rasterize(*params.values(), viewmat, K, size, size)
        ((colors - target) ** 2).sum().backward()
        return colors, alphas, meta

    # Load the numba kernels (from cache, or compile) on a tiny scene, so the baseline RSS includes them.
    tiny = make_gaussians(mesh, 100)
    rasterize(*tiny.values(), viewmat, K, 32, 32)[0].sum()
    rss_before = current_rss_mib()
    ours()
    ms, cpu_ms = time_iterations(ours, min_seconds=2.0, min_iters=3, max_iters=50)
    peak = peak_rss_mib()
    with torch.no_grad():
        colors, alphas, meta = rasterize(*params.values(), viewmat, K, size, size, visibility_counts=True)
    pairs = int(meta["visibility_counts"].sum())

    def baseline():
        for p in params.values():
            p.grad = None
        rgb, alpha = torch_tiled_rasterize(*params.values(), viewmat[0], K[0], size, size)
        ((rgb[None] - target) ** 2).sum().backward()
        return rgb, alpha

    torch_ms, _ = time_iterations(baseline, min_seconds=0.0, min_iters=torch_iters, max_iters=torch_iters)
    # The baseline is timed in float32; its image is compared in float64, where the two must agree.
    with torch.no_grad():
        g64 = [v.double() for v in g.values()]
        rgb, alpha = torch_tiled_rasterize(*g64, viewmat[0].double(), K[0].double(), size, size)
    return {
        "size": size,
        "n": n,
        "ms": ms,
        "cpu_ms": cpu_ms,
        "torch_ms": torch_ms,
        "peak_rss_mib": peak,
        "working_mib": peak - rss_before,
        "coverage": float((alphas > 0.5).float().mean()),
        "n_isects": meta["n_isects"],
        "pairs": pairs,
        "max_diff": float(max((colors[0] - rgb).abs().max(), (alphas[0, ..., 0] - alpha).abs().max())),
        "threads": torch.get_num_threads(),
    }


def run_production(mesh_path: Path, sh_degree: int | None, n_cams: int, width: int, height: int, n: int, focal: float) -> dict:
    """The `cpu` preset's per-iteration render: all training views in one batched call, forward and backward.

    sh_degree None is Stage I (alpha only: no colour channel, [N, 0], loss on alpha); 2 is Stage II (SH
    colours [N, 9, 3], a random background per view, loss on colour and alpha).
    """
    mesh, _ = load_mesh(mesh_path)
    g = make_gaussians(mesh, n)
    viewmats, Ks = ring_cameras(mesh, n_cams, width, height, focal)
    gen = torch.Generator().manual_seed(0)
    params = {k: g[k].clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities")}
    if sh_degree is None:
        colors = torch.zeros(n, 0)
    else:
        sh = 0.3 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=gen)
        sh[:, 0] = (g["colors"] - 0.5) / 0.28209479177387814
        colors = sh.requires_grad_(True)
    target_rgb = torch.rand(n_cams, height, width, 3, generator=gen)
    target_alpha = torch.rand(n_cams, height, width, 1, generator=gen)

    def forward():
        backgrounds = None if sh_degree is None else torch.rand(n_cams, 3, generator=gen)
        rgb, alpha, meta = rasterize(*params.values(), colors, viewmats, Ks, width, height, sh_degree=sh_degree, backgrounds=backgrounds)
        loss = (alpha - target_alpha).abs().mean()
        if sh_degree is not None:
            loss = loss + (rgb - target_rgb).abs().mean()
        return loss, alpha, meta

    def backward(loss):
        for p in [*params.values(), colors]:
            p.grad = None
        loss.backward()

    rasterize(*(v[:100] for v in params.values()), colors[:100], viewmats[:1], Ks[:1], 32, 32, sh_degree=sh_degree)
    for _ in range(2):
        backward(forward()[0])
    fwd, bwd, cpu = [], [], []
    start = time.perf_counter()
    while len(fwd) < 50 and (len(fwd) < 10 or time.perf_counter() - start < 4.0):
        t0, c0 = time.perf_counter(), time.process_time()
        loss, alpha, meta = forward()
        t1 = time.perf_counter()
        backward(loss)
        t2 = time.perf_counter()
        fwd.append(t1 - t0)
        bwd.append(t2 - t1)
        cpu.append(time.process_time() - c0)
    tiles = alpha.detach()[..., 0].unfold(1, 16, 16).unfold(2, 16, 16)
    return {
        "stage": "I (alpha)" if sh_degree is None else f"II (SH {sh_degree})",
        "views": n_cams,
        "width": width,
        "height": height,
        "n": n,
        "fwd_ms": 1e3 * float(np.median(fwd)),
        "bwd_ms": 1e3 * float(np.median(bwd)),
        "cpu_ms": 1e3 * float(np.median(cpu)),
        "tile_coverage": float((tiles.amax(dim=(-1, -2)) > 1.0 / 255.0).float().mean()),
        "n_isects": meta["n_isects"],
        "threads": torch.get_num_threads(),
    }


def machine_peak_gflops() -> tuple[float, str]:
    """fp64 FMA peak of the CPUs this process may use: cores x GHz x 2 FMA units x 4 lanes (AVX2) x 2."""
    cores = len(os.sched_getaffinity(0))
    cpuinfo = Path("/proc/cpuinfo").read_text()
    mhz = max(float(line.split(":")[1]) for line in cpuinfo.splitlines() if line.startswith("cpu MHz"))
    lanes = 8 if " avx512f " in cpuinfo else 4
    peak = cores * mhz / 1e3 * 2 * lanes * 2
    return peak, f"{cores} cores x {mhz / 1e3:.2f} GHz x 2 FMA units x {lanes} fp64 lanes x 2"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", type=Path, default=DEFAULT_MESH)
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--counts", type=int, nargs="+", default=[10_000, 20_000, 50_000, 200_000, 600_000])
    ap.add_argument("--out", type=Path, default=RESULTS / "rasterizer.md")
    ap.add_argument("--no-production", action="store_true", help="skip the batched production-shaped rows")
    ap.add_argument("--one", nargs=4, metavar=("SIZE", "N", "FOCAL", "TORCH_ITERS"), help=argparse.SUPPRESS)
    ap.add_argument("--production-one", choices=["alpha", "sh2"], help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        size, n, focal, torch_iters = int(args.one[0]), int(args.one[1]), float(args.one[2]), int(args.one[3])
        print(json.dumps(run_one(args.mesh, size, n, focal, torch_iters)))
        return 0
    if args.production_one:
        print(json.dumps(run_production(args.mesh, None if args.production_one == "alpha" else 2, **PRODUCTION)))
        return 0

    mesh, mesh_name = load_mesh(args.mesh)
    env = dict(os.environ)

    def subprocess_row(*extra: str) -> dict:
        cmd = [sys.executable, "-m", "benchmarks.bench_rasterizer", "--mesh", str(args.mesh), *extra]
        out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env, cwd=REPO).stdout
        row = json.loads(out.strip().splitlines()[-1])
        print(json.dumps(row), flush=True)
        return row

    anchor_before = anchor_ms()
    rows = []
    for size in args.sizes:
        focal, coverage = fit_focal(mesh, size)
        print(f"{size}x{size}: focal {focal:.1f} px gives {100 * coverage:.0f}% coverage", flush=True)
        for n in args.counts:
            torch_iters = 3 if n <= 20_000 else 1
            rows.append(subprocess_row("--one", str(size), str(n), str(focal), str(torch_iters)))
    production = [] if args.no_production else [subprocess_row("--production-one", v) for v in ("alpha", "sh2")]
    anchor_after = anchor_ms()
    anchor = 0.5 * (anchor_before + anchor_after)
    print(json.dumps({"anchor_ms_before": anchor_before, "anchor_ms_after": anchor_after}), flush=True)

    peak, peak_how = machine_peak_gflops()
    cores = len(os.sched_getaffinity(0))
    lines = [
        f"Rasterizer forward+backward (loss = squared error to a random image), one camera, Gaussians sampled "
        f"on {mesh_name} covering ~{100 * TARGET_COVERAGE:.0f}% of the image; {rows[0]['threads']} threads, "
        f"{openmp_wait(env)}; {cpu_line()}; load average {os.getloadavg()[0]:.1f} at the end. Times are "
        f"medians; CPU time sums all threads. The speed anchor's step (20k splats, 256², the tiled pure-torch rasterizer in "
        f"a child process, `reconstruction.render.anchor`) read {anchor_before:.0f} ms before the rows and {anchor_after:.0f} ms "
        f"after; `x anchor` is their mean over ours. Peak RSS is the whole process (Python, torch, the scene); in "
        f"brackets what the rasterizer's iterations added on top.",
        "",
        "| image | N | ours ms/iter | ours CPU ms/iter | tiled torch ms/iter | speed-up | x anchor | peak RSS MiB (rasterizer) "
        "| coverage | tile isects | shaded pairs | GFLOP/s | max abs diff |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    best = 0.0
    for r in rows:
        gflops = r["pairs"] * FLOPS_PER_PAIR / (r["ms"] * 1e-3) / 1e9
        # Per busy core: the work over the CPU time, against one core's share of the peak.
        best = max(best, r["pairs"] * FLOPS_PER_PAIR / (r["cpu_ms"] * 1e-3) / 1e9)
        lines.append(
            f"| {r['size']}² | {r['n'] // 1000}k | {r['ms']:.1f} | {r['cpu_ms']:.1f} | {r['torch_ms']:.0f} "
            f"| {r['torch_ms'] / r['ms']:.0f}x | {anchor / r['ms']:.0f}x "
            f"| {r['peak_rss_mib']:.0f} ({r['working_mib']:.0f}) | {100 * r['coverage']:.0f}% | {r['n_isects']:,} "
            f"| {r['pairs']:,} | {gflops:.2f} | {r['max_diff']:.1e} |"
        )
    lines += [
        "",
        f"FLOP bound: this machine's fp64 peak is {peak:.0f} GFLOP/s ({peak_how}), {peak / cores:.0f} per core. "
        f"At ~{FLOPS_PER_PAIR} flops per shaded pixel-Gaussian pair, the GFLOP/s column is over wall time; per "
        f"busy core (over CPU time) the best row reaches {best:.2f} GFLOP/s, {100 * best * cores / peak:.1f}% of "
        f"a core's peak. The rasterizer is bound by latency (scalar, branchy "
        f"front-to-back compositing, whose per-pixel transmittance recurrence does not vectorise), memory "
        f"(gathers of splats and per-pixel state) and the O(N) projection and binning passes, not by arithmetic.",
    ]
    if production:
        p = PRODUCTION
        lines += [
            "",
            f"Production-shaped batch (the `cpu` preset's training render): {p['n_cams']} views at {p['width']}x"
            f"{p['height']} on a ring 35° above {mesh_name}, {p['n'] // 1000}k splats, every view in one call, "
            f"loss = L1 to random targets. Stage I renders alpha only (no colour channel, as training renders it; a zero [N, 1] colour before 2026-11-27 11:00 UTC); "
            f"Stage II SH degree 2 with a random background per view. Forward and backward timed apart "
            f"(medians); CPU time sums all threads; `x anchor`: the anchor step over forward + backward.",
            "",
            "| stage | forward ms | backward ms | CPU ms/iter | x anchor | tiles covered | tile isects |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in production:
            lines.append(
                f"| {r['stage']} | {r['fwd_ms']:.1f} | {r['bwd_ms']:.1f} | {r['cpu_ms']:.1f} | {anchor / (r['fwd_ms'] + r['bwd_ms']):.1f}x "
                f"| {100 * r['tile_coverage']:.0f}% | {r['n_isects']:,} |"
            )
    table = "\n".join(lines) + "\n"
    print()
    print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())

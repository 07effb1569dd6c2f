"""Benchmarks: one script per capability, each run from the repository root as
`python -m benchmarks.bench_<thing>`; each prints a markdown table and writes it to benchmarks/results/."""

from reconstruction.parallel import configure_openmp

# As the `cadsplat` command does before torch loads (deploy/cli.py): idle OpenMP workers spin only briefly before they
# sleep, leaving the rasterizer's threads their cores. Timed without it, the engine is not the one users run (rig
# scenes, `preview`, clamp and banana: 12.7 and 11.4 s per capture under libgomp's default ~3 ms spin, 10.5-10.8 and
# 9.0 s with none).
configure_openmp()

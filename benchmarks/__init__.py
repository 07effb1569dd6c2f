"""Benchmarks: one script per capability, each run from the repository root as
`python -m benchmarks.bench_<thing>`; each prints a markdown table and writes it to benchmarks/results/."""

"""`cadsplat worker run|join`: reconstruction jobs on a Ray cluster."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import click


@click.group(help="Reconstruction on a Ray cluster (tasks ask for a GPU where the cluster has one).")
def worker() -> None:
    pass


@worker.command("run", help="Reconstruct every CAPTURE concurrently on the cluster; one twin directory each under OUT.")
@click.argument("captures", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option("--library", "library", required=True, type=click.Path(exists=True, path_type=Path))
@click.option("--out", "out", required=True, type=click.Path(path_type=Path))
@click.option("--preset", default="cpu", type=click.Choice(["preview", "cpu", "paper"]), show_default=True)
@click.option(
    "--cluster", "address", default=None, help="Ray address (ray://host:10001, host:6379 or auto); default: a local Ray on this machine."
)
@click.option("--retries", default=2, show_default=True, help="Ray retries of a failed task before it is reported failed.")
def run(captures: tuple[Path, ...], library: Path, out: Path, preset: str, address: str | None, retries: int) -> None:
    from deploy.cluster import connect, run_tasks
    from deploy.steps import PipelineConfig, process_capture

    names = [c.resolve().name for c in captures]
    if len(set(names)) != len(names):
        raise click.ClickException("capture directory names must be unique: each names its twin's folder")
    resources = connect(address)
    click.echo(f"cluster: {resources.get('CPU', 0):.0f} CPU, {resources.get('GPU', 0):.0f} GPU")
    cfg = PipelineConfig(str(library.resolve()), preset)
    jobs = [(name, (str(c.resolve()), str((out / name).resolve()), cfg), {}) for name, c in zip(names, captures)]
    results = run_tasks(
        process_capture,
        jobs,
        max_retries=retries,
        on_result=lambda r: click.echo(f"{r.status:<6} {r.key} {r.error or r.output['reconstruct']['twin']}"),
    )
    failed = [r for r in results if r.status != "done"]
    if failed:
        raise click.ClickException(f"{len(failed)} of {len(results)} captures failed: " + "; ".join(f"{r.key}: {r.error}" for r in failed))


@worker.command(
    "join",
    help="Make this machine a worker node of the Ray cluster at ADDRESS (blocks until stopped). "
    "Token authentication is required (RAY_AUTH_MODE=token unless set): the token comes from RAY_AUTH_TOKEN or Ray's token file.",
)
@click.option("--cluster", "address", required=True, help="The head node, host:6379.")
@click.option("--num-gpus", default=None, type=int, help="GPUs to offer (default: what Ray detects).")
def join(address: str, num_gpus: int | None) -> None:
    ray_bin = shutil.which("ray") or str(Path(sys.executable).with_name("ray"))
    cmd = [ray_bin, "start", f"--address={address}", "--block"] + ([f"--num-gpus={num_gpus}"] if num_gpus is not None else [])
    # A node joins only a cluster that authenticates (Ray before 2.61 leaves a started head open unless asked).
    raise SystemExit(subprocess.call(cmd, env={"RAY_AUTH_MODE": "token", **os.environ}))

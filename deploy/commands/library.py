"""`cadsplat library build MESH_DIR --out LIB` and `cadsplat library list LIB`: the CAD library and its silhouette index."""

from __future__ import annotations

import time
from pathlib import Path

import click

from calibration.units import UNIT_TO_M


@click.group(help="Build and inspect a CAD library's silhouette index.")
def library() -> None:
    pass


@library.command(help="Index every mesh (OBJ, STL, PLY, GLB) under MESH_DIR into the library LIB; models already indexed are kept.")
@click.argument("mesh_dir", type=click.Path(path_type=Path))
@click.option("--out", "out_dir", required=True, type=click.Path(path_type=Path), help="Library directory (created or updated).")
@click.option(
    "--unit",
    default="m",
    show_default=True,
    type=click.Choice(list(UNIT_TO_M)),
    help="Unit of meshes that do not declare their own (name.units<u>.ext or units.json).",
)
@click.option("--workers", default=None, type=click.IntRange(1, 256), help="Parallel render processes (default: all cores).")
@click.option("--progress/--no-progress", default=True, show_default=True, help="Show a progress bar.")
def build(mesh_dir: Path, out_dir: Path, unit: str, workers: int | None, progress: bool) -> None:
    from reconstruction.library import build_library

    if not mesh_dir.is_dir():
        raise click.ClickException(f"mesh directory {mesh_dir} does not exist")
    t0 = time.perf_counter()
    lib = build_library(mesh_dir, out_dir, unit=unit, workers=workers, progress=progress, log=lambda line: click.echo(line, err=True))
    size = sum(m.shard.stat().st_size for m in lib.models)
    click.echo(
        f"library {out_dir}: {len(lib.models)} models, {len(lib.skipped)} skipped, {lib.grid.n_dirs} views per model, "
        f"{size / max(len(lib.models), 1) / 1024:.0f} KiB per model, built in {time.perf_counter() - t0:.1f} s"
    )


@library.command(name="list", help="List the models of the library LIB.")
@click.argument("lib_dir", type=click.Path(path_type=Path))
def list_models(lib_dir: Path) -> None:
    from reconstruction.library import load_library

    lib = load_library(lib_dir)
    for m in lib.models:
        ext = " x ".join(f"{e * 1000:.1f}" for e in m.extent_m)
        parts = f"{len(m.part_names)} parts" if m.part_names else f"{m.components} components"
        click.echo(f"{m.id}\t{m.unit}\t{ext} mm\t{parts}")
    for s in lib.skipped:
        click.echo(f"skipped {s['file']}: {s['reason']}")

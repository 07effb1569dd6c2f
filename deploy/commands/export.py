"""`cadsplat export TWIN --format FMT --out PATH`: a twin in the formats other tools read."""

from __future__ import annotations

import importlib
from pathlib import Path

import click

# format -> ("module:function", help). Each function takes (twin_dir, out) and returns the written path.
FORMATS: dict[str, tuple[str, str]] = {
    "ply": ("deploy.commands.export:export_ply", "the splats as an Inria 3DGS PLY (opens in 3DGS viewers)"),
    "glb": ("deploy.commands.export:export_glb", "the deformed CAD mesh, one node per part"),
    "mjcf": ("simulation.export:export_mjcf", "a MuJoCo model package"),
    "colmap": ("simulation.export:export_colmap", "a COLMAP sparse model of the twin's cameras"),
}


def _copy_atomic(src: Path, out: Path) -> Path:
    from calibration.fileio import atomic_write_bytes

    if out.is_dir():
        out = out / src.name
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out, src.read_bytes())
    return out


def export_ply(twin_dir: Path, out: Path) -> Path:
    from reconstruction.twin import SPLATS_PLY, load_twin

    twin = load_twin(twin_dir)  # validates the twin before anything is written
    return _copy_atomic(twin.root / SPLATS_PLY, out)


def export_glb(twin_dir: Path, out: Path) -> Path:
    from reconstruction.twin import TwinError, load_twin

    twin = load_twin(twin_dir)
    if not twin.mesh_deformed_path.exists():
        raise TwinError(f"{twin.mesh_deformed_path}: the twin has no deformed mesh to export")
    return _copy_atomic(twin.mesh_deformed_path, out)


@click.command(help="Export the twin at TWIN as " + ", ".join(f"{k} ({v[1]})" for k, v in FORMATS.items()) + ".")
@click.argument("twin_dir", type=click.Path(path_type=Path))
@click.option("--format", "fmt", required=True, type=click.Choice(list(FORMATS)), help="Output format.")
@click.option("--out", "out", required=True, type=click.Path(path_type=Path), help="Output file or directory.")
def export(twin_dir: Path, fmt: str, out: Path) -> None:
    module, attr = FORMATS[fmt][0].split(":")
    written = getattr(importlib.import_module(module), attr)(twin_dir, out)
    click.echo(f"{fmt} written to {written}")


"""`cadsplat export TWIN --format FMT --out PATH`: a twin in the formats other tools read.

Every export is atomic: a file is written beside its name and renamed; a directory format (mjcf,
colmap) is built in a hidden sibling directory and renamed into place, so a full disk or a kill
leaves the old output or none, never a partial tree. An existing output is replaced only with
`--overwrite`, and only when it holds an export of that format.
"""

from __future__ import annotations

import importlib
from pathlib import Path

import click

# The file every export of a directory format holds: what makes a directory "an export of that format".
DIRECTORY_MARKERS = {"mjcf": "model.xml", "colmap": "cameras.txt"}

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


def write_export(fmt: str, twin_dir: Path, out: Path, *, overwrite: bool = False) -> Path:
    """Export the twin at `twin_dir` as `fmt` to `out`, atomically; returns what was written."""
    import os
    import shutil
    import tempfile

    from calibration.fileio import fsync_dir
    from reconstruction.twin import load_twin

    module, attr = FORMATS[fmt][0].split(":")
    exporter = getattr(importlib.import_module(module), attr)
    if fmt not in DIRECTORY_MARKERS:
        if out.exists() and not out.is_dir() and not overwrite:
            raise click.ClickException(f"{out} already exists; pass --overwrite to replace it")
        return exporter(twin_dir, out)
    if out.exists():
        if not overwrite:
            raise click.ClickException(f"{out} already exists; pass --overwrite to replace it")
        if not (out / DIRECTORY_MARKERS[fmt]).is_file():
            raise click.ClickException(f"{out} holds no {fmt} export (no {DIRECTORY_MARKERS[fmt]}), so it is not replaced; choose another --out")
    load_twin(twin_dir)  # a damaged twin fails here, before anything is written
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".incoming", dir=out.parent))
    try:
        exporter(twin_dir, tmp)
        fsync_dir(tmp)
        old = None
        if out.exists():
            old = out.parent / f".{out.name}.replaced"
            shutil.rmtree(old, ignore_errors=True)
            os.rename(out, old)
        os.rename(tmp, out)
        fsync_dir(out.parent)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


@click.command(help="Export the twin at TWIN as " + ", ".join(f"{k} ({v[1]})" for k, v in FORMATS.items()) + ".")
@click.argument("twin_dir", type=click.Path(path_type=Path))
@click.option("--format", "fmt", required=True, type=click.Choice(list(FORMATS)), help="Output format.")
@click.option("--out", "out", required=True, type=click.Path(path_type=Path), help="Output file or directory.")
@click.option("--overwrite", is_flag=True, help="Replace an existing export of this format at --out.")
def export(twin_dir: Path, fmt: str, out: Path, overwrite: bool) -> None:
    written = write_export(fmt, twin_dir, out, overwrite=overwrite)
    click.echo(f"{fmt} written to {written}")


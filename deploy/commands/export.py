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
    "glb": ("deploy.commands.export:export_glb", "the deformed CAD mesh, one node per part, +Y up"),
    "mjcf": ("simulation.export:export_mjcf", "a MuJoCo model package"),
    "usd": ("simulation.export:export_usd", "a USD rigid body with mass and collision (Isaac Sim)"),
    "colmap": ("simulation.export:export_colmap", "a COLMAP sparse model of the twin's cameras"),
}


def _write_atomic(data: bytes, out: Path, name: str) -> Path:
    from calibration.fileio import atomic_write_bytes

    if out.is_dir():
        out = out / name
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out, data)
    return out


def export_ply(twin_dir: Path, out: Path) -> Path:
    """The splats re-encoded as the current PLY layout (SH padded to degree 3, so Inria's loader
    reads it without --sh_degree), also for twins saved before the padding."""
    from reconstruction.twin import SPLATS_PLY, load_twin, splat_normals, splats_to_ply_bytes

    twin = load_twin(twin_dir)  # validates the twin before anything is written
    data = splats_to_ply_bytes(twin.means, twin.quats, twin.log_scales, twin.opacity_logits, twin.sh, splat_normals(twin.quats))
    return _write_atomic(data, out, SPLATS_PLY)


def export_glb(twin_dir: Path, out: Path) -> Path:
    """The deformed mesh re-encoded +Y up (parts under the object-frame root node), also for twins
    whose GLB was saved z up."""
    from reconstruction.mesh_io import parts_glb_bytes
    from reconstruction.twin import TwinError, load_twin

    twin = load_twin(twin_dir)
    if not twin.mesh_deformed_path.exists():
        raise TwinError(f"{twin.mesh_deformed_path}: the twin has no deformed mesh to export")
    return _write_atomic(parts_glb_bytes(twin.load_mesh_deformed()), out, twin.mesh_deformed_path.name)


# Formats that carry a rigid body take the physics options; the others ignore them.
PHYSICS_FORMATS = ("mjcf", "usd")


def _physics(density: float | None, material: str | None, rig_toml: Path | None) -> dict:
    """The simulation formats' keyword arguments from the command's options (None: not given)."""
    return {"density": density, "material": material, "rig_toml": rig_toml}


def write_export(fmt: str, twin_dir: Path, out: Path, *, overwrite: bool = False, **options) -> Path:
    """Export the twin at `twin_dir` as `fmt` to `out`, atomically; returns what was written.
    `options` go to the format's exporter (the physics options of `PHYSICS_FORMATS`)."""
    import shutil
    import tempfile

    from calibration.fileio import fsync_dir, publish_dir
    from reconstruction.twin import load_twin

    module, attr = FORMATS[fmt][0].split(":")
    exporter = getattr(importlib.import_module(module), attr)
    if fmt not in DIRECTORY_MARKERS:
        if out.exists() and not out.is_dir() and not overwrite:
            raise click.ClickException(f"{out} already exists; pass --overwrite to replace it")
        return exporter(twin_dir, out, **options)
    if out.exists():
        if not overwrite:
            raise click.ClickException(f"{out} already exists; pass --overwrite to replace it")
        if not (out / DIRECTORY_MARKERS[fmt]).is_file():
            raise click.ClickException(f"{out} holds no {fmt} export (no {DIRECTORY_MARKERS[fmt]}), so it is not replaced; choose another --out")
    load_twin(twin_dir)  # a damaged twin fails here, before anything is written
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".incoming", dir=out.parent))
    try:
        exporter(twin_dir, tmp, **options)
        fsync_dir(tmp)
        publish_dir(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


@click.command(help="Export the twin at TWIN as " + ", ".join(f"{k} ({v[1]})" for k, v in FORMATS.items()) + ".")
@click.argument("twin_dir", type=click.Path(path_type=Path))
@click.option("--format", "fmt", required=True, type=click.Choice(list(FORMATS)), help="Output format.")
@click.option("--out", "out", required=True, type=click.Path(path_type=Path), help="Output file or directory.")
@click.option("--density", type=float, default=None, help="mjcf/usd: density in kg/m^3 (overrides the material).")
@click.option("--material", default=None, help="mjcf/usd: material name (plastic, steel, aluminium, ...) giving the density.")
@click.option("--rig", "rig_toml", type=click.Path(dir_okay=False, path_type=Path), default=None, help="mjcf/usd: rig.toml whose [simulation] table gives the density.")
@click.option("--overwrite", is_flag=True, help="Replace an existing export of this format at --out.")
def export(twin_dir: Path, fmt: str, out: Path, density: float | None, material: str | None, rig_toml: Path | None, overwrite: bool) -> None:
    options = _physics(density, material, rig_toml) if fmt in PHYSICS_FORMATS else {}
    written = write_export(fmt, twin_dir, out, overwrite=overwrite, **options)
    click.echo(f"{fmt} written to {written}")


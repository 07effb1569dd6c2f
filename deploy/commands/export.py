"""`cadsplat export TWIN --format FMT --out PATH`: a twin in the formats other tools read."""

from __future__ import annotations

import importlib
from pathlib import Path

import click

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
    from reconstruction.twin import TwinError, load_twin, parts_glb_bytes

    twin = load_twin(twin_dir)
    if not twin.mesh_deformed_path.exists():
        raise TwinError(f"{twin.mesh_deformed_path}: the twin has no deformed mesh to export")
    return _write_atomic(parts_glb_bytes(twin.load_mesh_deformed()), out, twin.mesh_deformed_path.name)


# Formats that carry a rigid body take the physics options; the others ignore them.
PHYSICS_FORMATS = ("mjcf", "usd")


def _physics(density: float | None, material: str | None, rig_toml: Path | None) -> dict:
    """The simulation formats' keyword arguments from the command's options (None: not given)."""
    return {"density": density, "material": material, "rig_toml": rig_toml}


@click.command(help="Export the twin at TWIN as " + ", ".join(f"{k} ({v[1]})" for k, v in FORMATS.items()) + ".")
@click.argument("twin_dir", type=click.Path(path_type=Path))
@click.option("--format", "fmt", required=True, type=click.Choice(list(FORMATS)), help="Output format.")
@click.option("--out", "out", required=True, type=click.Path(path_type=Path), help="Output file or directory.")
@click.option("--density", type=float, default=None, help="mjcf/usd: density in kg/m^3 (overrides the material).")
@click.option("--material", default=None, help="mjcf/usd: material name (plastic, steel, aluminium, ...) giving the density.")
@click.option("--rig", "rig_toml", type=click.Path(dir_okay=False, path_type=Path), default=None, help="mjcf/usd: rig.toml whose [simulation] table gives the density.")
def export(twin_dir: Path, fmt: str, out: Path, density: float | None, material: str | None, rig_toml: Path | None) -> None:
    module, attr = FORMATS[fmt][0].split(":")
    kwargs = _physics(density, material, rig_toml) if fmt in PHYSICS_FORMATS else {}
    written = getattr(importlib.import_module(module), attr)(twin_dir, out, **kwargs)
    click.echo(f"{fmt} written to {written}")


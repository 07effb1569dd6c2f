"""`cadsplat export TWIN --format FMT --out PATH`: a twin in the formats other tools read.

The formats, their exporters and the atomic write are `simulation.export` (`FORMATS`,
`write_export`), shared with the service's export step; this module is the command line.
"""

from __future__ import annotations

from pathlib import Path

import click

from simulation.export import FORMATS, PHYSICS_FORMATS, ExportError, write_export


@click.command(help="Export the twin at TWIN as " + ", ".join(f"{k} ({v[1]})" for k, v in FORMATS.items()) + ".")
@click.argument("twin_dir", type=click.Path(path_type=Path))
@click.option("--format", "fmt", required=True, type=click.Choice(list(FORMATS)), help="Output format.")
@click.option("--out", "out", required=True, type=click.Path(path_type=Path), help="Output file or directory.")
@click.option("--density", type=float, default=None, help="mjcf/usd: density in kg/m^3 (overrides the material).")
@click.option("--material", default=None, help="mjcf/usd: material name (plastic, steel, aluminium, ...) giving the density.")
@click.option("--rig", "rig_toml", type=click.Path(dir_okay=False, path_type=Path), default=None, help="mjcf/usd: rig.toml whose [simulation] table gives the density.")
@click.option("--overwrite", is_flag=True, help="Replace an existing export of this format at --out.")
def export(twin_dir: Path, fmt: str, out: Path, density: float | None, material: str | None, rig_toml: Path | None, overwrite: bool) -> None:
    options = {"density": density, "material": material, "rig_toml": rig_toml} if fmt in PHYSICS_FORMATS else {}
    try:
        written = write_export(fmt, twin_dir, out, overwrite=overwrite, **options)
    except ExportError as e:
        raise click.ClickException(str(e)) from None
    click.echo(f"{fmt} written to {written}")

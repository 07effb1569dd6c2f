"""`cadsplat export TWIN --format FMT --out PATH`: a twin in the formats other tools read.

The formats, their exporters and the atomic write are `simulation.export` (`FORMATS`,
`write_export`), shared with the service's export step; this module is the command line.
"""

from __future__ import annotations

from pathlib import Path

import click

from simulation.export import FORMATS, PHYSICS_FORMATS, UP_FORMATS, ExportError, write_export


@click.command(help="Export the twin at TWIN as " + ", ".join(f"{k} ({v[1]})" for k, v in FORMATS.items()) + ".")
@click.argument("twin_dir", type=click.Path(path_type=Path))
@click.option("--format", "fmt", required=True, type=click.Choice(list(FORMATS)), help="Output format.")
@click.option("--out", "out", required=True, type=click.Path(path_type=Path), help="Output file or directory.")
@click.option("--density", type=float, default=None, help="mjcf/usd: density in kg/m^3 (overrides the material).")
@click.option("--material", default=None, help="mjcf/usd: material name (plastic, steel, aluminium, ...) giving the density.")
@click.option(
    "--hull-budget",
    type=click.IntRange(1, 10000),
    default=None,
    help="mjcf/usd: most convex hulls in the collision decomposition (default: rig.toml's, else 32).",
)
@click.option(
    "--rig",
    "rig_toml",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="glb/spz/mjcf/usd: rig.toml whose [simulation] table gives the density, hull budget and up direction.",
)
@click.option(
    "--cad-up-axis",
    default=None,
    help="glb/spz/mjcf/usd: the CAD model's up axis (+y, z, -x, ...) when neither the twin nor rig.toml says which way is up.",
)
@click.option("--mesh", is_flag=True, help="glb: the deformed CAD mesh alongside the splats.")
@click.option("--overwrite", is_flag=True, help="Replace an existing export of this format at --out.")
def export(
    twin_dir: Path,
    fmt: str,
    out: Path,
    density: float | None,
    material: str | None,
    hull_budget: int | None,
    rig_toml: Path | None,
    cad_up_axis: str | None,
    mesh: bool,
    overwrite: bool,
) -> None:
    options: dict = {}
    if fmt in UP_FORMATS:
        options.update(rig_toml=rig_toml, cad_up_axis=cad_up_axis)
    if fmt in PHYSICS_FORMATS:
        options.update(density=density, material=material, hull_budget=hull_budget)
    if fmt == "glb":
        options["mesh"] = mesh
    if cad_up_axis is not None:
        from simulation.up import axis_vector

        try:
            axis_vector(cad_up_axis)
        except ValueError as e:
            raise click.BadParameter(str(e), param_hint="--cad-up-axis") from None
    try:
        written = write_export(fmt, twin_dir, out, overwrite=overwrite, **options)
    except ExportError as e:
        raise click.ClickException(str(e)) from None
    click.echo(f"{fmt} written to {written}")

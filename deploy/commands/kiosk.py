"""`cadsplat kiosk [--simulate]`: the operator screen."""

from __future__ import annotations

import os
from pathlib import Path

import click


@click.command(help="The operator screen: rig, calibration, captures, twins and alarms in one terminal (80x24 is enough).")
@click.option("--simulate", is_flag=True, help="Run the whole appliance on the synthetic rig (no hardware needed).")
@click.option(
    "--config", "config", default=None, type=click.Path(exists=True, path_type=Path), help="The rig's rig.toml (real cameras and trigger)."
)
@click.option("--library", "library", default=None, type=click.Path(exists=True, path_type=Path), help="CAD library (with --config).")
@click.option(
    "--work",
    "work",
    default=None,
    type=click.Path(path_type=Path),
    help="Where captures, calibration and twins go (default: a temporary folder).",
)
@click.option("--preset", default="preview", type=click.Choice(["preview", "cpu"]), show_default=True)
@click.option("--interval", default=20.0, show_default=True, help="Seconds between parts while watching the line.")
@click.option("--no-color", is_flag=True, help="Plain text, no colours (also NO_COLOR=1).")
def kiosk(
    simulate: bool, config: Path | None, library: Path | None, work: Path | None, preset: str, interval: float, no_color: bool
) -> None:
    if simulate == (config is not None):
        raise click.ClickException("choose one: --simulate, or --config rig.toml --library LIB --work DIR")
    if no_color:
        os.environ["NO_COLOR"] = "1"
    from deploy.appliance import Appliance
    from deploy.kiosk import Kiosk

    if simulate:
        click.echo("starting the simulated appliance (building the CAD library, opening 8 synthetic cameras)...")
        backend = Appliance.simulated(work, preset=preset, interval_s=interval)
    else:
        if library is None or work is None:
            raise click.ClickException("--config needs --library LIB and --work DIR")
        from calibration.guard import LockHeld

        try:
            backend = Appliance.from_config(config, library, work, preset=preset, interval_s=interval)
        except LockHeld as e:
            raise click.ClickException(f"{e} (one writer per store)") from None
    try:
        Kiosk(backend).run()
    finally:
        backend.close()

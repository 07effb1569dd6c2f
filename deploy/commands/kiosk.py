"""`cadsplat kiosk [--simulate]`: the operator screen."""

from __future__ import annotations

import os
from pathlib import Path

import click


@click.command(help="The operator screen: rig, calibration, captures, twins and alarms in one terminal (80x24 is enough).")
@click.option("--simulate", is_flag=True, help="Run the whole appliance on the synthetic rig (no hardware needed).")
@click.option("--work", "work", default=None, type=click.Path(path_type=Path), help="Where captures, calibration and twins go (default: a temporary folder).")
@click.option("--preset", default="preview", type=click.Choice(["preview", "cpu"]), show_default=True)
@click.option("--interval", default=20.0, show_default=True, help="Seconds between parts while watching the line.")
@click.option("--no-color", is_flag=True, help="Plain text, no colours (also NO_COLOR=1).")
def kiosk(simulate: bool, work: Path | None, preset: str, interval: float, no_color: bool) -> None:
    if not simulate:
        raise click.ClickException("only --simulate is available without a configured rig; run 'cadsplat kiosk --simulate'")
    if no_color:
        os.environ["NO_COLOR"] = "1"
    from deploy.appliance import SimulatedAppliance
    from deploy.kiosk import Kiosk

    click.echo("starting the simulated appliance (building the CAD library, opening 8 synthetic cameras)...")
    backend = SimulatedAppliance(work, preset=preset, interval_s=interval)
    try:
        Kiosk(backend).run()
    finally:
        backend.close()

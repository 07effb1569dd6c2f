"""`cadsplat synth MESH --out DIR`: the synthetic rig photographs a textured mesh (train + held-out + gt.json)."""

from __future__ import annotations

import re
import time
from pathlib import Path

import click


def parse_size(text: str) -> tuple[int, int]:
    """'320x240' -> (320, 240); anything else is a ClickException in one sentence."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or int(m[1]) < 8 or int(m[2]) < 8 or int(m[1]) > 8192 or int(m[2]) > 8192:
        raise click.ClickException(f"--size must be WIDTHxHEIGHT with both between 8 and 8192 pixels (like 320x240), got '{text}'")
    return int(m[1]), int(m[2])


@click.command(help="Render a textured mesh from a synthetic rig into DIR/train, DIR/heldout and DIR/gt.json.")
@click.argument("mesh", type=click.Path(path_type=Path))
@click.option(
    "--out", "out_dir", required=True, type=click.Path(path_type=Path), help="Output directory (its train/ and heldout/ must not exist)."
)
@click.option("--views", default=9, show_default=True, type=click.IntRange(1, 200), help="Train views (rig cameras).")
@click.option("--heldout", default=36, show_default=True, type=click.IntRange(0, 1000), help="Held-out orbit views.")
@click.option("--size", default="320x240", show_default=True, help="Image size WIDTHxHEIGHT.")
@click.option("--seed", default=0, show_default=True, type=int, help="Seeds object pose, calibration error, lighting and noise.")
@click.option(
    "--calib-noise-deg",
    default=0.0,
    show_default=True,
    type=click.FloatRange(0, 45),
    help="Sigma of the rotation error added to recorded train extrinsics.",
)
@click.option(
    "--calib-noise-mm",
    default=0.0,
    show_default=True,
    type=click.FloatRange(0, 1000),
    help="Sigma of the centre error added to recorded train extrinsics.",
)
@click.option(
    "--backdrop/--no-backdrop", default=False, show_default=True, help="Textured conveyor floor and sky instead of a flat background."
)
@click.option(
    "--noise",
    "noise_std",
    default=0.0,
    show_default=True,
    type=click.FloatRange(0, 1),
    help="Sensor noise sigma, in full-scale units (0.01 = 2.55 grey levels).",
)
@click.option(
    "--lighting-jitter",
    default=0.0,
    show_default=True,
    type=click.FloatRange(0, 1),
    help="Per-view change of the key light (0 = fixed lamp).",
)
@click.option(
    "--yaw", "object_yaw_deg", default=None, type=float, help="Object yaw on the conveyor, degrees (default: drawn from the seed)."
)
def synth(
    mesh: Path,
    out_dir: Path,
    views: int,
    heldout: int,
    size: str,
    seed: int,
    calib_noise_deg: float,
    calib_noise_mm: float,
    backdrop: bool,
    noise_std: float,
    lighting_jitter: float,
    object_yaw_deg: float | None,
) -> None:
    width, height = parse_size(size)
    if not mesh.is_file():
        raise click.ClickException(f"mesh file {mesh} does not exist")
    for sub in ("train", "heldout"):
        if (out_dir / sub).exists():
            raise click.ClickException(f"{out_dir / sub} already exists; choose a new --out (captures are never overwritten)")

    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from rig.synthetic import synth_dataset

    console = Console(stderr=True)
    t0 = time.perf_counter()
    with Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=console, transient=True
    ) as bar:
        tasks: dict[str, int] = {}

        def progress(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(f"rendering {stage}", total=total)
            bar.update(tasks[stage], completed=done)

        gt = synth_dataset(
            mesh,
            out_dir,
            views=views,
            heldout=heldout,
            size=(width, height),
            seed=seed,
            calib_noise_deg=calib_noise_deg,
            calib_noise_mm=calib_noise_mm,
            backdrop=backdrop,
            noise_std=noise_std,
            lighting_jitter=lighting_jitter,
            object_yaw_deg=object_yaw_deg,
            progress=progress,
        )
    wall = time.perf_counter() - t0
    n = gt["views"] + gt["heldout"]
    s = gt["sim3_rig_to_object"]
    click.echo(
        f"Synthesized {gt['mesh_name']}: {gt['views']} train + {gt['heldout']} held-out views at {width}x{height} in {wall:.1f} s ({wall / n:.2f} s per view)."
    )
    click.echo(f"  train    {out_dir / 'train'}  (images, masks, empty-rig backgrounds; recorded poses in the rig frame)")
    if gt["heldout"]:
        click.echo(f"  heldout  {out_dir / 'heldout'}")
    click.echo(
        f"  truth    {out_dir / 'gt.json'}  (rig->object Sim(3) scale {s['scale']:.3f}, object yaw {gt['object_pose']['yaw_deg']:.1f} deg)"
    )
    if calib_noise_deg or calib_noise_mm:
        click.echo(f"  calibration error on recorded train extrinsics: sigma {calib_noise_deg} deg, {calib_noise_mm} mm")

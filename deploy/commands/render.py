"""`cadsplat render TWIN --views CAPTURE | --orbit N --out DIR`: RGBA renders of a twin."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import click
import numpy as np


def orbit_cameras(twin, n: int):
    """n object-frame cameras on a turntable circle at the training cameras' mean distance and
    elevation, looking at the splats' centre, with the first training camera's intrinsics."""
    from calibration.camera import look_at_c2w

    means = twin.gaussians.means
    centre = 0.5 * (means.min(0) + means.max(0))
    cams = [c.camera for c in twin.cameras]
    offsets = np.stack([c.center for c in cams]) - centre
    radius = float(np.median(np.linalg.norm(offsets, axis=1)))
    # The rig's "up" is the mean camera -y axis (OpenCV y points down in the image).
    up = -np.mean([c.c2w[:3, 1] for c in cams], axis=0)
    up /= max(np.linalg.norm(up), 1e-12)
    elev = float(np.median(np.arcsin(np.clip((offsets @ up) / np.linalg.norm(offsets, axis=1), -1, 1))))
    a = np.cross(up, [1.0, 0, 0]) if abs(up[0]) < 0.9 else np.cross(up, [0, 1.0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    out = []
    for k in range(n):
        phi = 2 * np.pi * k / n
        eye = centre + radius * (np.cos(elev) * (np.cos(phi) * a + np.sin(phi) * b) + np.sin(elev) * up)
        out.append((f"orbit_{k:03d}.png", cams[0].with_c2w(look_at_c2w(eye, centre, up))))
    return out


@click.command(help="Render the twin at TWIN from a capture's cameras (rig frame) or a turntable orbit; writes DIR/<name>.png as RGBA.")
@click.argument("twin_dir", type=click.Path(path_type=Path))
@click.option(
    "--views", "views_dir", default=None, type=click.Path(path_type=Path), help="Capture whose cameras (rig frame) to render from."
)
@click.option("--orbit", default=None, type=click.IntRange(1, 3600), help="Render a turntable of N views instead.")
@click.option("--out", "out_dir", default=None, type=click.Path(path_type=Path), help="Directory for the PNGs.")
@click.option(
    "--explode",
    default=0.0,
    show_default=True,
    type=float,
    help="Move parts away from the assembly centre by this fraction (an exploded view).",
)
@click.option("--hide-part", "hidden", multiple=True, help="Leave this part (name or index) out; repeatable.")
@click.option("--list-parts", is_flag=True, help="List the twin's parts and their splat counts, render nothing.")
@click.option(
    "--refine-steps",
    default=0,
    show_default=True,
    type=click.IntRange(0, 10000),
    help="Test-time pose refinement steps per view against the capture's own images (the twin stays frozen).",
)
def render(
    twin_dir: Path,
    views_dir: Path | None,
    orbit: int | None,
    out_dir: Path | None,
    explode: float,
    hidden: tuple[str, ...],
    list_parts: bool,
    refine_steps: int,
) -> None:
    from calibration.capture import read_capture
    from reconstruction.twin import load_twin
    from simulation.parts import exploded_splats
    from simulation.parts import list_parts as twin_parts

    if list_parts:
        for index, name, count in twin_parts(load_twin(twin_dir)):
            click.echo(f"{index:>3}  {name:<32} {count:>8} splats")
        return
    if out_dir is None:
        raise click.ClickException("--out DIR is required to render")
    if (views_dir is None) == (orbit is None):
        raise click.ClickException("give exactly one of --views CAPTURE or --orbit N")
    if orbit is not None and refine_steps:
        raise click.ClickException("--refine-steps needs --views: an orbit has no photographs to refine against")
    twin = load_twin(twin_dir)
    gaussians = exploded_splats(twin, explode, hidden)[0] if explode or hidden else twin.gaussians
    if views_dir is not None:
        capture = read_capture(views_dir)
        jobs = [
            (Path(f.file_path).name, capture.camera(i).with_c2w(twin.sim3_rig_to_object.apply_to_c2w(f.camera.c2w)), i)
            for i, f in enumerate(capture.frames)
        ]
    else:
        capture = None
        jobs = [(name, cam, None) for name, cam in orbit_cameras(twin, orbit)]
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    # Every image is rendered into a hidden sibling first, so a full disk or a kill leaves no partial set.
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".incoming", dir=out_dir.parent))
    try:
        _render_all(jobs, twin, gaussians, capture, refine_steps, tmp)
        _publish(tmp, out_dir)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    click.echo(f"{len(jobs)} RGBA images written to {out_dir}")


def _publish(tmp: Path, out_dir: Path) -> None:
    """Move the rendered set into `out_dir`: one rename when it is new, else one rename per image."""
    import os

    from calibration.fileio import fsync_dir

    if not out_dir.exists():
        os.rename(tmp, out_dir)
    else:
        for p in sorted(tmp.iterdir()):
            os.replace(p, out_dir / p.name)
        fsync_dir(out_dir)
    fsync_dir(out_dir.parent)


def _render_all(jobs, twin, gaussians, capture, refine_steps: int, folder: Path) -> None:
    from rich.progress import track

    from calibration.fileio import atomic_write_png
    from reconstruction.gaussians import camera_batch, render, straight_rgba

    masks = None
    if refine_steps and capture is not None:
        from reconstruction.masks import capture_masks

        # Once for the whole capture: its own masks (masks/ or alpha) when every view has one, else background subtraction.
        own = [capture.mask(i) for i in range(len(capture))]
        masks = own if all(m is not None for m in own) else capture_masks(capture)[0]
    for name, cam, i in track(jobs, description="rendering", transient=True):
        if refine_steps and capture is not None:
            from reconstruction.evaluation import refine_camera_pose

            ref = refine_camera_pose(twin.gaussians, cam, capture.image(i), masks[i], steps=refine_steps)
            cam = cam.with_c2w(ref.c2w)
        rgba = straight_rgba(*render(gaussians, *camera_batch(cam), background=None))[0]
        atomic_write_png(folder / f"{Path(name).stem}.png", rgba)

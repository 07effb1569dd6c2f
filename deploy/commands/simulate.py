"""`cadsplat simulate SCENE.toml --out DIR`: MuJoCo run of twins (or CAD meshes), rendered with their Gaussians.

DIR receives `mjcf/` (the package MuJoCo ran, loadable in its viewer), `poses.json` (every body's
pose per frame, energies, penetration), `frames/frame_NNNN.png` and `simulation.gif` (or `.mp4`).
"""

from __future__ import annotations

import io
import os
import sys
import tempfile
import time
from pathlib import Path

import click
import numpy as np

from calibration.fileio import atomic_write_bytes, atomic_write_json, encode_png, fsync_dir


def _write_video(path: Path, frames: np.ndarray, fps: float) -> None:
    """Animated GIF (imageio) or MP4 (OpenCV's writer), written beside `path` and renamed into place."""
    if path.suffix == ".gif":
        import imageio.v3 as iio

        buf = io.BytesIO()
        iio.imwrite(buf, frames, extension=".gif", duration=1000.0 / fps, loop=0)
        atomic_write_bytes(path, buf.getvalue())
        return
    import cv2

    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".mp4", dir=path.parent)
    os.close(fd)
    try:
        h, w = frames.shape[1:3]
        writer = cv2.VideoWriter(tmp, cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
        if not writer.isOpened():
            raise click.ClickException("this OpenCV build cannot write MP4; use --video gif")
        for f in frames:
            writer.write(np.ascontiguousarray(f[..., ::-1]))
        writer.release()
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        fsync_dir(path.parent)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


@click.command()
@click.argument("scene_toml", type=click.Path(path_type=Path))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path), help="Output directory (new or empty).")
@click.option("--video", type=click.Choice(["gif", "mp4"]), default="gif", show_default=True, help="Animation format.")
@click.option("--no-render", is_flag=True, help="Simulate and write poses only (no Gaussian renders).")
@click.option(
    "--decompose/--no-decompose",
    default=True,
    show_default=True,
    help="Allow CoACD decomposition for concave bodies (else their convex hull).",
)
@click.option(
    "--coacd-threshold",
    type=click.FloatRange(min=0.01, max=1.0),
    default=0.05,
    show_default=True,
    help="CoACD's first concavity threshold; lowered while the pieces miss the volume tolerance.",
)
@click.option(
    "--coacd-timeout",
    type=click.FloatRange(min=1.0),
    default=300.0,
    show_default=True,
    help="Seconds CoACD may spend per part (all runs) before the best so far, or the hull, is used.",
)
def simulate(
    scene_toml: Path, out_dir: Path, video: str, no_render: bool, decompose: bool, coacd_threshold: float, coacd_timeout: float
) -> None:
    """Run SCENE_TOML in MuJoCo and render every frame with the twins' Gaussians."""
    from simulation.collision import DecompositionOptions
    from simulation.export import load_body
    from simulation.follow import camera_path, render_trajectory
    from simulation.mjcf import write_mjcf_package
    from simulation.run import load_model
    from simulation.run import simulate as run_simulation
    from simulation.scene import load_scene

    scene = load_scene(scene_toml)
    if out_dir.exists() and any(out_dir.iterdir()):
        raise click.ClickException(f"{out_dir} already holds files; choose a new or empty directory so nothing is overwritten")
    out_dir.mkdir(parents=True, exist_ok=True)
    decomposition = DecompositionOptions(threshold=coacd_threshold, timeout_s=coacd_timeout) if decompose else None
    t0 = time.perf_counter()
    bodies, splats = [], []
    for p in scene.placements:
        body, s = load_body(p, decomposition)
        bodies.append(body)
        splats.append(s)
        click.echo(f"{p.name}: {body.asset.mass.mass:.4g} kg, collision {body.collision.kind} ({body.collision.notes[0]})")
    xml = write_mjcf_package(out_dir / "mjcf", bodies, scene.options)
    traj = run_simulation(load_model(xml), scene.duration, scene.fps)
    t_sim = time.perf_counter() - t0
    atomic_write_json(out_dir / "poses.json", {"scene": str(scene_toml.resolve()), "fps": scene.fps, **traj.to_dict()})
    click.echo(f"simulated {scene.duration:g} s ({len(traj.times)} frames) in {t_sim:.1f} s; final kinetic energy {traj.kinetic[-1]:.3g} J")
    if no_render:
        return
    # MuJoCo lists bodies in the order they were written, which is the scene's order.
    cams = camera_path(scene.camera, len(traj.times))
    (out_dir / "frames").mkdir(exist_ok=True)
    frames = []
    with click.progressbar(range(len(traj.times)), label="rendering", file=sys.stderr) as bar:
        poses = traj.poses()
        for f in bar:
            frame = render_trajectory(splats, poses[f : f + 1], cams[f : f + 1])[0]
            atomic_write_bytes(out_dir / "frames" / f"frame_{f:04d}.png", encode_png(frame))
            frames.append(frame)
    fsync_dir(out_dir / "frames")
    _write_video(out_dir / f"simulation.{video}", np.stack(frames), scene.fps)
    click.echo(f"wrote {len(frames)} frames and {out_dir / f'simulation.{video}'}")

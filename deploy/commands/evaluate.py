"""`cadsplat evaluate TWIN --views HELDOUT --out metrics.json`: the paper's evaluation protocol (4.3)."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING

import click

if TYPE_CHECKING:
    import numpy as np

    from calibration.camera import Camera
    from reconstruction.twin import Twin

SUMMARY = ("psnr", "ssim", "lpips", "mpsnr", "mlpips", "fgpsnr", "iou")


def _fmt(x: float | None) -> str:
    return "   n/a" if x is None or not math.isfinite(x) else f"{x:6.3f}"


@click.command(
    help="Score the twin at TWIN on the held-out capture's views (their cameras in the rig frame) with the "
    "paper's protocol, with and without test-time pose refinement, and write every metric to --out."
)
@click.argument("twin_dir", type=click.Path(path_type=Path))
@click.option("--views", "views_dir", required=True, type=click.Path(path_type=Path), help="Held-out capture (with masks/).")
@click.option("--out", "out_path", required=True, type=click.Path(path_type=Path), help="metrics.json to write.")
@click.option(
    "--refine-steps",
    default=400,
    show_default=True,
    type=click.IntRange(0, 100_000),
    help="Test-time pose refinement steps per view (0 scores only the nominal poses).",
)
@click.option(
    "--gt",
    "gt_path",
    default=None,
    type=click.Path(path_type=Path),
    help="gt.json of a synthetic rig: also score the twin's training-camera registration.",
)
@click.option(
    "--symmetry",
    "symmetry_axes",
    multiple=True,
    type=click.Choice(["x", "y", "z"]),
    help="With --gt: the object looks the same turned 180 deg about this object axis; registration errors "
    "are taken against the closer pose (repeatable).",
)
@click.option(
    "--near-symmetries",
    "symmetry_mm",
    default=None,
    type=click.FloatRange(min=0.0, min_open=True),
    help="With --gt: find the turns that move the twin's mesh by less than MM (mean surface distance, e.g. the "
    "rig's calibration noise) and take registration errors against the closest of them.",
)
@click.option(
    "--max-views",
    default=None,
    type=click.IntRange(1, 100_000),
    help="Score at most N held-out views, evenly spread over the capture (default: all).",
)
def evaluate(
    twin_dir: Path,
    views_dir: Path,
    out_path: Path,
    refine_steps: int,
    gt_path: Path | None,
    symmetry_axes: tuple[str, ...],
    symmetry_mm: float | None,
    max_views: int | None,
) -> None:
    """Score the twin on the held-out views, write metrics.json and print the summary."""
    from calibration.capture import load_views, read_capture
    from calibration.fileio import atomic_write_json
    from reconstruction.evaluation import select_views
    from reconstruction.twin import load_twin

    if out_path.exists() and out_path.is_dir():
        raise click.ClickException(f"--out {out_path} is a directory; give a file name such as metrics.json")
    t0 = time.perf_counter()
    twin = load_twin(twin_dir)
    capture = read_capture(views_dir)
    if not capture.has_masks:
        raise click.ClickException(f"held-out capture {views_dir} has no masks; the protocol needs a ground-truth mask per view")
    gt = _read_gt(gt_path)
    if (symmetry_axes or symmetry_mm) and gt is None:
        raise click.ClickException(
            "--symmetry and --near-symmetries need --gt: symmetries only change how registration errors are measured"
        )
    symmetries, labels = _symmetries(twin, symmetry_axes, symmetry_mm)
    idx = select_views(len(capture), max_views)
    images, masks, cams = load_views(capture, idx)
    names = [Path(capture.frames[i].file_path).stem for i in idx]
    t_load = time.perf_counter() - t0

    report = _evaluate_with_progress(twin, cams, images, masks, names, refine_steps, gt, symmetries)
    report["timings_s"]["load"] = t_load
    doc = {
        "twin": str(twin_dir),
        "views": str(views_dir),
        "protocol": "paper 4.3: object crop (10%-padded square, Lanczos 256) psnr/ssim/lpips/flip; 5-px eroded mask "
        "mpsnr/mssim/mlpips/mflip; fgpsnr; iou (alpha > 0.5); None = undefined or infinite",
        "model_id": twin.model_id,
        "preset": twin.preset,
        "refine_steps": refine_steps,
        "num_views": len(idx),
        "train_timings_s": twin.timings_s,
        **report,
    }
    atomic_write_json(out_path, doc)
    _echo_summary(twin, report, len(idx), refine_steps, labels, out_path)


def _read_gt(gt_path: Path | None) -> dict | None:
    """The synthetic rig's gt.json at gt_path (None without one); ClickException when unreadable or not a rig's."""
    if gt_path is None:
        return None
    try:
        gt = json.loads(Path(gt_path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise click.ClickException(f"cannot read --gt {gt_path} ({e.__class__.__name__})") from None
    if "train_c2w_object" not in gt:
        raise click.ClickException(f"--gt {gt_path} has no train_c2w_object; is it a synthetic rig's gt.json?")
    return gt


def _symmetries(twin: Twin, symmetry_axes: tuple[str, ...], symmetry_mm: float | None) -> tuple[list[np.ndarray], list[str]]:
    """The object-frame symmetry transforms to score registration against, and a phrase describing each."""
    from reconstruction.evaluation import half_turn, twin_near_symmetries

    symmetries = [half_turn(a) for a in symmetry_axes]
    labels = [f"the pose turned 180 deg about {a}" for a in symmetry_axes]
    if symmetry_mm:
        try:
            found = twin_near_symmetries(twin, symmetry_mm * 1e-3)
        except ValueError as e:
            raise click.ClickException(str(e)) from None
        symmetries += [s.transform for s in found]
        labels += [f"the pose turned {s.angle_deg:.1f} deg, a near-symmetry moving the mesh {1e3 * s.deviation:.2f} mm" for s in found]
    return symmetries, labels


def _evaluate_with_progress(
    twin: Twin,
    cams: list[Camera],
    images: np.ndarray,
    masks: np.ndarray,
    names: list[str],
    refine_steps: int,
    gt: dict | None,
    symmetries: list[np.ndarray],
) -> dict:
    """evaluate_twin's report on the views (images [V, H, W, 3], masks [V, H, W]), with a progress bar on stderr."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from reconstruction.evaluation import evaluate_twin

    console = Console(stderr=True)
    with Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=console, transient=True
    ) as bar:
        task = bar.add_task(f"evaluating ({refine_steps} refinement steps per view)", total=len(names))
        return evaluate_twin(
            twin,
            cams,
            images,
            masks,
            names=names,
            refine_steps=refine_steps,
            gt=gt,
            symmetries=symmetries or None,
            progress=lambda done, _total: bar.update(task, completed=done),
        )


def _echo_summary(twin: Twin, report: dict, num_views: int, refine_steps: int, labels: list[str], out_path: Path) -> None:
    """Print the mean metrics (nominal and refined) and the registration errors to stdout."""
    click.echo(
        f"Evaluated {twin.model_id} ({twin.num_splats} splats, preset {twin.preset}) on {num_views} held-out views "
        f"in {report['timings_s']['total']:.1f} s ({report['timings_s']['per_view_render_ms']:.0f} ms per render)."
    )
    click.echo("              " + " ".join(f"{k:>6}" for k in SUMMARY))
    click.echo("  nominal     " + " ".join(_fmt(report["mean"][k]) for k in SUMMARY))
    if refine_steps:
        click.echo("  refined     " + " ".join(_fmt(report["mean_refined"][k]) for k in SUMMARY))
    if "registration" in report:
        r = report["registration"]
        sym = "" if r["symmetry"] is None else f" (against {labels[r['symmetry']]})"
        click.echo(
            f"  registration of {len(r['cameras'])} training cameras: median {r['rotation_deg_median']:.2f} deg, "
            f"{r['center_pct_median']:.2f} % of distance{sym}"
        )
    click.echo(f"  metrics per view and averaged: {out_path}")

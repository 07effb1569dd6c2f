"""`cadsplat inspect TWIN [--tolerance MM] [--out DIR] [--capture CAPTURE]`: where the twin departs from its CAD model.

Prints one line on stdout, the verdict, and exits with a code a PLC can act on:

    0  PASS       every seen vertex inside the tolerance by more than its uncertainty, at most --max-unseen % of
                  the surface unseen
    1  FAIL       a seen vertex departs by more than the tolerance plus its uncertainty (the worst is named: part,
                  mm +- uncertainty, where)
    2  error      the twin could not be inspected (missing meshes, bad arguments); one sentence on stderr
    3  UNCERTAIN  nothing seen is certainly out of tolerance, but more than --max-unseen % of the surface was unseen
                  (another capture, more views, can decide)
    4  UNCERTAIN  the surface is covered, nothing is certainly out, but some seen vertex lies within its uncertainty
                  of the tolerance (named: vertex, part, mm +- uncertainty, where; a finer measurement decides)

Every seen vertex carries the expanded (k = 2) uncertainty of its deviation, from the views that see it (their
angles and pixel size at the vertex) and the map's local fit residual (`reconstruction.inspect`). With --capture
the capture's masks, at the camera's own resolution, refine the map at the part's outlines
(`reconstruction.inspect_silhouette`; measured in benchmarks/results/inspect_truth*.md).

Unseen shares name the part no camera has in view at all (the rig's coverage, which no recapture changes):
`UNCERTAIN 26 % of the surface unseen (25 % in no camera's view); ...`.

DIR (default TWIN/inspection) is replaced as a whole, atomically:

    inspection.json       verdict, settings, per-part summary, sha256 of every file below
    parts/<part>.csv      one row per CAD vertex: position and deviation (mm), its uncertainty (mm, k = 2), status
                          (ok / out / uncertain / unseen), views, best angle, pixel size at the vertex (mm), local
                          fit residual (mm), area, cameras in view
    deviation.ply         the CAD mesh (metres) with vertex colours, deviation_mm, uncertainty_mm, views per vertex
    deviation.glb         the same colours, one node per part
    views/<view>.png      heat map from every training viewpoint; turntable/orbit_NNN.png; legend.png
"""

from __future__ import annotations

from pathlib import Path

import click

from deploy.inspection_report import DEFAULT_MAX_UNSEEN_PCT, DEFAULT_TOLERANCE_MM, inspect_twin_dir
from reconstruction.inspect import MAX_ANGLE_DEG


@click.command(
    help="Measure how the twin at TWIN departs from its CAD model, where, and how much of it the cameras saw. "
    "Prints the verdict on stdout and exits 0 PASS, 1 FAIL, 3 UNCERTAIN (too much unseen), 4 UNCERTAIN (a seen vertex "
    "within its uncertainty of the tolerance); 2: could not inspect."
)
@click.argument("twin_dir", type=click.Path(path_type=Path))
@click.option(
    "--tolerance",
    "tolerance_mm",
    default=DEFAULT_TOLERANCE_MM,
    show_default=True,
    type=click.FloatRange(min=0.0, min_open=True),
    help="Allowed deviation from the CAD surface, mm (either way).",
)
@click.option(
    "--max-unseen",
    "max_unseen_pct",
    default=DEFAULT_MAX_UNSEEN_PCT,
    show_default=True,
    type=click.FloatRange(0.0, 100.0),
    help="Largest share of the surface (%) the cameras may miss before the verdict is UNCERTAIN.",
)
@click.option("--out", "out_dir", default=None, type=click.Path(path_type=Path), help="Report directory (default: TWIN/inspection).")
@click.option("--turntable", default=24, show_default=True, type=click.IntRange(0, 360), help="Turntable heat-map views (0: none).")
@click.option(
    "--max-angle",
    "max_angle_deg",
    default=MAX_ANGLE_DEG,
    show_default=True,
    type=click.FloatRange(1.0, 89.0),
    help="A camera sees a surface point only when the surface normal is within this angle of its line of sight.",
)
@click.option(
    "--capture",
    "capture_dir",
    default=None,
    type=click.Path(path_type=Path),
    help="The capture the twin was made from: its masks, at the camera's own resolution, refine the map at the part's outlines.",
)
def inspect(
    twin_dir: Path,
    tolerance_mm: float,
    max_unseen_pct: float,
    out_dir: Path | None,
    turntable: int,
    max_angle_deg: float,
    capture_dir: Path | None,
) -> None:
    out = out_dir if out_dir is not None else twin_dir / "inspection"
    doc = inspect_twin_dir(
        twin_dir,
        out,
        tolerance_mm=tolerance_mm,
        max_unseen_pct=max_unseen_pct,
        turntable=turntable,
        max_angle_deg=max_angle_deg,
        capture_dir=capture_dir,
    )
    for p in doc["parts"]:
        worst = "unseen" if p["worst_mm"] is None else f"worst {p['worst_mm']:+.2f} mm, p95 |dev| {p['p95_abs_mm']:.2f} mm"
        seen = (
            "" if p["views_median"] is None else f", seen by {p['views_median']:.0f} views (median) at {p['best_angle_median_deg']:.0f} deg"
        )
        click.echo(
            f"  {p['name']:<24} {worst}; {p['out_of_tolerance_pct']:.2f} % out of tolerance, {p['unseen_pct']:.0f} % unseen "
            f"({p['out_of_view_pct']:.0f} % in no camera's view), "
            f"{p['single_view_pct']:.0f} % seen by one view only{seen}",
            err=True,
        )
    click.echo(f"  report: {out}", err=True)
    v = doc["verdict"]
    click.echo(v["line"])
    raise click.exceptions.Exit(v["exit_code"])

"""Collision geometry: speed against error, per shared mesh, and the 2 s drop each choice gives.

For every YCB object (metres) and CAD part (declared units) it reports the volume error
(V_geom - V_mesh) / V_mesh of the convex hull, the best enclosing primitive and one CoACD run at
the first threshold (input decimated to 4000 faces, time-capped), the pieces and seconds each took,
what `collision_geometry` chose at the default 10 % tolerance within the hull budget (CoACD's piece
count chosen by that error, at most --hull-budget pieces) with its Hausdorff distance to the mesh
and the volume error left at the budget, and a 2 s drop with that choice (final kinetic energy,
resting and peak impact penetration, lowest mesh point above the floor). Every time is followed by its
ratio to the speed anchor's step read at the start of the run (`benchmarks._common.machine_reading`),
whose ms, CPU and load the header states.

    python -m benchmarks.bench_collision [--timeout 120] [--threshold 0.05] [--hull-budget 32] [--only NAME ...] [--out FILE.md]

Prints a markdown table and writes benchmarks/results/collision.md (or --out) and a plot beside it.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._common import RESULTS, SHARED, MachineReading, load_line, machine_reading
from simulation.asset import load_mesh_asset
from simulation.collision import (
    DECOMPOSE_FACES,
    DEFAULT_HULL_BUDGET,
    DEFAULT_TOLERANCE,
    CollisionGeometry,
    DecompositionOptions,
    collision_geometry,
    convex_volume,
    decompose,
    hull_vertices,
    primitive_candidates,
    surface_points,
)
from simulation.mjcf import BodySpec, write_mjcf_package
from simulation.run import load_model, rest_report, simulate
from simulation.scene import euler_xyz_to_quat, resting_position

YCB = [
    "011_banana",
    "033_spatula",
    "037_scissors",
    "043_phillips_screwdriver",
    "050_medium_clamp",
    "061_foam_brick",
    "072-c_toy_airplane",
    "077_rubiks_cube",
]
PARTS = {
    "1002_tray_bottom.STL": "mm",
    "ADIS16480.STL": "m",
    "angle_block.STL": "in",
    "counter.unitsmm.STL": None,
    "featuretype.STL": "in",
    "idler_riser.STL": "in",
    "large_block.STL": "mm",
    "octagonal_pocket.stl": "m",
    "plate_holes.STL": "mm",
    "round.stl": "mm",
    "torus.STL": "in",
    "busted.STL": "mm",
}


def meshes(only: list[str]) -> list[tuple[str, Path, str | None]]:
    out = [(n, SHARED / "objects" / "ycb" / n / "textured.obj", "m") for n in YCB]
    out += [(n.split(".")[0], SHARED / "cad" / "parts" / n, u) for n, u in PARTS.items()]
    return [m for m in out if m[1].exists() and (not only or m[0] in only)]


def drop(asset, col: CollisionGeometry, workdir: Path):
    quat = euler_xyz_to_quat((20.0, 10.0, 0.0))
    pos = resting_position(asset.vertices, quat, (0.0, 0.0, 0.0), 0.05)
    model = load_model(write_mjcf_package(workdir / asset.name, [BodySpec(asset, col, pos, quat)]))
    t0 = time.perf_counter()
    traj = simulate(model, 2.0, fps=50)
    sim_s = time.perf_counter() - t0
    return rest_report(traj, 0, asset.vertices, asset.mass.center_of_mass, surface_points(col)), sim_s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--timeout", type=float, default=300.0, help="CoACD seconds per mesh (all runs)")
    ap.add_argument("--threshold", type=float, default=0.05, help="CoACD's first concavity threshold")
    ap.add_argument("--hull-budget", type=int, default=DEFAULT_HULL_BUDGET, help="most convex pieces per body")
    ap.add_argument("--only", nargs="*", default=[])
    ap.add_argument("--out", type=Path, default=RESULTS / "collision.md")
    args = ap.parse_args()
    opts = DecompositionOptions(threshold=args.threshold, timeout_s=args.timeout, hull_budget=args.hull_budget)
    machine = machine_reading()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, path, unit in meshes(args.only):
            asset = load_mesh_asset(path, unit, name.replace("-", "_"))
            vol = asset.mass.volume
            t0 = time.perf_counter()
            hull = hull_vertices(asset.vertices)
            hull_err, hull_s = convex_volume(hull) / vol - 1, time.perf_counter() - t0
            t0 = time.perf_counter()
            prim = min(primitive_candidates(hull), key=lambda p: p.volume)
            prim_err, prim_s = prim.volume / vol - 1, time.perf_counter() - t0
            t0 = time.perf_counter()
            pieces = decompose(asset.vertices, asset.faces, opts)
            dec_s = time.perf_counter() - t0
            dec_err = np.nan if not pieces else sum(convex_volume(p) for p in pieces) / vol - 1
            chosen = collision_geometry(asset.vertices, asset.faces, vol, face_part=asset.face_part, decomposition=opts)
            rep, sim_s = drop(asset, chosen, Path(tmp))
            rows.append(
                {
                    "mesh": name,
                    "faces": len(asset.faces),
                    "extent_m": float(np.ptp(asset.vertices, 0).max()),
                    "hull_err": hull_err,
                    "hull_s": hull_s,
                    "prim": prim.kind,
                    "prim_err": prim_err,
                    "prim_s": prim_s,
                    "pieces": len(pieces) if pieces else 0,
                    "dec_err": dec_err,
                    "dec_s": dec_s,
                    "chosen": chosen.kind,
                    "chosen_err": chosen.volume_error,
                    "chosen_pieces": chosen.hull_count + len(chosen.primitives),
                    "chosen_s": chosen.seconds,
                    "hausdorff_mm": 1e3 * chosen.hausdorff,
                    "ke_ratio": rep.kinetic_ratio,
                    "rest_pen_mm": 1e3 * rep.final_penetration,
                    "peak_pen_mm": 1e3 * rep.peak_penetration,
                    "lowest_mm": 1e3 * rep.lowest_height,
                    "support_mm": 1e3 * rep.support_margin,
                    "sim_s": sim_s,
                }
            )
            print(
                f"{name}: hull {100 * hull_err:.1f}%, {prim.kind} {100 * prim_err:.1f}%, CoACD {rows[-1]['pieces']} pieces {100 * dec_err:.1f}% in {dec_s:.1f} s",
                flush=True,
            )
    table = render_table(rows, opts, machine, f"{load_line()} at the end")
    print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(table)
    plot(rows, args.out.with_suffix(".png"))


def render_table(rows: list[dict], opts: DecompositionOptions, machine: MachineReading, load_at_end: str) -> str:
    head = (
        f"# Collision geometry: speed against error (CoACD first threshold {opts.threshold}, {opts.timeout_s:.0f} s cap, "
        f"input decimated to {DECOMPOSE_FACES} faces, hull budget {opts.hull_budget})\n\n"
        f"Volume error = (V_union - V_mesh) / V_mesh. Chosen = `collision_geometry` at {100 * DEFAULT_TOLERANCE:.0f} % tolerance, per CAD part "
        f"(primitive, else hull, else CoACD at falling thresholds until the error is within tolerance, at most {opts.hull_budget} pieces: "
        "runs over the budget send the threshold back up, and the chosen error is the one left at the budget), with the Hausdorff distance "
        f"between its surface and the mesh's. Drop: 2 s from 5 cm, tilted 20/10 deg, MuJoCo timestep 1 ms. {machine.header()} "
        f"Each time is followed by its `x anchor` in brackets; {load_at_end}.\n\n"
        "| mesh | faces | size m | hull err | best primitive | prim err | CoACD 1st run pieces | err | s (x anchor) | chosen (shapes) | chosen err "
        "| Hausdorff mm | chosen s (x anchor) | final KE / peak | rest pen. mm | impact pen. mm | lowest pt mm | COM off support mm | sim s (x anchor) |\n"
        "|---|---:|---:|---:|---|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    )
    pct = lambda x: "timeout" if not np.isfinite(x) else f"{100 * x:.1f}%"  # noqa: E731
    x = machine.x_anchor
    lines = [
        f"| {r['mesh']} | {r['faces']} | {r['extent_m']:.3g} | {pct(r['hull_err'])} | {r['prim']} | {pct(r['prim_err'])} | {r['pieces']} "
        f"| {pct(r['dec_err'])} | {r['dec_s']:.1f} ({x(r['dec_s'])}) | {r['chosen']} ({r['chosen_pieces']}) | {pct(r['chosen_err'])} "
        f"| {r['hausdorff_mm']:.2f} | {r['chosen_s']:.1f} ({x(r['chosen_s'])}) | {r['ke_ratio']:.1e} "
        f"| {r['rest_pen_mm']:.4f} | {r['peak_pen_mm']:.2f} | {r['lowest_mm']:.3f} | {r['support_mm']:.2f} | {r['sim_s']:.2f} ({x(r['sim_s'])}) |"
        for r in rows
    ]
    return head + "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for key, t_key, label, marker in [
        ("hull_err", "hull_s", "convex hull", "o"),
        ("prim_err", "prim_s", "best primitive", "s"),
        ("dec_err", "dec_s", "CoACD", "^"),
    ]:
        x = [max(r[t_key], 1e-4) for r in rows if np.isfinite(r[key])]
        y = [100 * abs(r[key]) for r in rows if np.isfinite(r[key])]
        ax.scatter(x, y, marker=marker, label=label)
    ax.set_xscale("log")
    ax.set_yscale("symlog", linthresh=1)
    ax.set_xlabel("seconds per mesh")
    ax.set_ylabel("|collision volume error| (%)")
    ax.set_title("Collision geometry: speed against error (shared meshes)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()

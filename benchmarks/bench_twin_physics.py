"""Simulation-ready twins against the truth: the rig_scenes twins exported as MuJoCo bodies.

For every scene of ../shared/data/rig_scenes with a twin in --twins (cadsplat twin directories,
one per scene name), at one density (ABS, 1050 kg/m^3; every ratio below is density-free):
- mass and principal inertia MuJoCo computes from the exported MJCF (`inertia="exact"`), against
  density x the true mesh (gt_mesh.ply; voxel-filled at 1 mm where it is open), and against the
  twin's own repaired mesh (what the exporter can be held to);
- the CAD variant's and the twin mesh's volume against the true one (where a mass error comes from);
- the collision geometry: kind, hulls, volume error, Hausdorff to the twin surface, seconds;
- the GLB export in the Khronos glTF validator (errors; "n/a" when it is not installed — set
  CADSPLAT_GLTF_VALIDATOR to a directory holding node_modules/gltf-validator), and the USD export
  read back by pxr (`check_usd`) with its mass against MuJoCo's.

    python -m benchmarks.bench_twin_physics [--twins ../twins_base] [--only SCENE ...]

Writes benchmarks/results/twin_physics.md.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh
from pxr import Usd, UsdPhysics

from benchmarks._common import REPO, RESULTS, SHARED, load_line
from simulation.export import export_glb
from simulation.asset import repair_mesh
from simulation.collision import DecompositionOptions
from simulation.export import twin_body
from simulation.mjcf import SimOptions, write_mjcf_package
from simulation.run import SimulationError, load_model
from simulation.usd import write_usd

RIG_SCENES = SHARED / "rig_scenes"
VOXEL_M = 1e-3


def true_solid(path: Path) -> tuple[float, np.ndarray, np.ndarray, str]:
    """(volume m^3, centre of mass [3], inertia [3, 3] at unit density, how) of the true mesh:
    exact when it is closed, else its 1 mm voxel filling (each filled voxel a point mass plus its
    own cube inertia)."""
    mesh = trimesh.load(path, process=False)
    mesh.merge_vertices()
    if mesh.is_volume:
        return float(mesh.volume), np.asarray(mesh.center_mass), np.asarray(mesh.moment_inertia), "closed mesh"
    vox = mesh.voxelized(VOXEL_M).fill()
    pts = np.asarray(vox.points)
    m = VOXEL_M**3
    com = pts.mean(0)
    d = pts - com
    inertia = m * (np.eye(3) * (d * d).sum() - d.T @ d) + len(pts) * m * VOXEL_M**2 / 6 * np.eye(3)
    return len(pts) * m, com, inertia, f"voxels {1e3 * VOXEL_M:g} mm"


def worst(deviation: np.ndarray) -> float:
    """The signed deviation of largest magnitude (principal moments compared in ascending order)."""
    return float(deviation[np.argmax(np.abs(deviation))])


def gltf_errors(glb: Path) -> str:
    """Error count of the Khronos glTF validator on `glb`, or "n/a" when node or the validator is absent."""
    node = shutil.which("node")
    root = os.environ.get("CADSPLAT_GLTF_VALIDATOR", "")
    if not root and shutil.which("npm"):
        root = subprocess.run(["npm", "root", "-g"], capture_output=True, text=True).stdout.strip()
    mods = Path(root) if Path(root).name == "node_modules" else Path(root) / "node_modules"
    if node is None or not root or not (mods / "gltf-validator").is_dir():
        return "n/a"
    js = ("const fs=require('fs');require('gltf-validator').validateBytes(new Uint8Array(fs.readFileSync(process.argv[1])))"
          ".then(r=>console.log(JSON.stringify(r.issues)))")
    res = subprocess.run([node, "-e", js, str(glb)], capture_output=True, text=True, env={**os.environ, "NODE_PATH": str(mods)}, timeout=300)
    if res.returncode != 0:
        return "failed"
    issues = json.loads(res.stdout)
    return f"{issues['numErrors']} err / {issues['numWarnings']} warn"


def measure(scene: str, twin_dir: Path, work: Path, decomposition: DecompositionOptions) -> dict:
    t0 = time.perf_counter()
    body = twin_body(twin_dir, decomposition=decomposition)
    export_s = time.perf_counter() - t0
    a, col = body.asset, body.collision
    rho = a.density.value
    row = {"scene": scene, "repair": "; ".join(a.repair.summary()), "export_s": export_s}
    try:
        model = load_model(write_mjcf_package(work / "mjcf", [body], SimOptions()))
        row["exact_loads"] = "yes"
        mj_mass, mj_inertia = float(model.body_mass[1]), np.sort(model.body_inertia[1])
    except SimulationError as e:
        row["exact_loads"] = f"no: {e}"
        mj_mass, mj_inertia = np.nan, np.full(3, np.nan)
    v_true, _, i_true, how = true_solid(RIG_SCENES / "scenes" / scene / "gt_mesh.ply")
    cad = trimesh.load(RIG_SCENES / "library" / f"{scene}.obj", force="mesh", process=False)
    cv, cf, _, _ = repair_mesh(cad.vertices, cad.faces)
    row.update(
        true_from=how,
        mass_vs_true=mj_mass / (rho * v_true) - 1,
        inertia_vs_true=worst(mj_inertia / np.sort(np.linalg.eigvalsh(rho * i_true)) - 1),
        mass_vs_twin=mj_mass / a.mass.mass - 1,
        inertia_vs_twin=worst(mj_inertia / np.sort(a.mass.principal_moments) - 1),
        vol_cad=trimesh.Trimesh(cv, cf, process=False).volume / v_true - 1,
        vol_twin=a.mass.volume / v_true - 1,
        col_kind=col.kind, hulls=col.hull_count, col_err=col.volume_error, hausdorff_mm=1e3 * col.hausdorff, col_s=col.seconds,
    )
    glb = export_glb(twin_dir, work / "twin.glb")
    row["gltf"] = gltf_errors(glb)
    usd = write_usd(work / "twin.usda", body)  # raises UsdCheckError unless pxr reads it back as the body
    stage = Usd.Stage.Open(str(usd))  # held: its prims live only as long as the stage
    row["usd_mass_vs_mjcf"] = UsdPhysics.MassAPI(stage.GetDefaultPrim()).GetMassAttr().Get() / mj_mass - 1
    return row


def render_table(rows: list[dict], load: str) -> str:
    pct = lambda x: "n/a" if not np.isfinite(x) else f"{100 * x:+.1f}%"  # noqa: E731
    head = (
        "# Twins as simulation bodies: mass, inertia and contact geometry against the truth\n\n"
        f"rig_scenes twins (cadsplat twin directories), exported with `simulation.export.twin_body` at 1050 kg/m^3; "
        f"mass and principal inertia as MuJoCo computes them from the MJCF (`inertia=\"exact\"`). Load: {load}.\n\n"
        "- *vs true*: against density x the true mesh (gt_mesh.ply, closed, so no voxel filling was needed); acceptance 3 % mass, 5 % inertia "
        "(inertia: the principal moment, ascending order, furthest off, with its sign).\n"
        "- *vs twin*: against the twin's own repaired mesh: what the exporter computes (exactness of the physics export).\n"
        "- *V cad / V twin*: volume of the repaired CAD variant and of the twin's deformed mesh against the true volume: "
        "where a mass error comes from.\n"
        "- collision: chosen at 10 % volume tolerance; Hausdorff between the collision set's surface and the twin mesh's.\n\n"
        "| scene | exact loads | mass vs true | inertia vs true | mass vs twin | inertia vs twin | V cad | V twin "
        "| collision | hulls | coll. vol err | Hausdorff mm | coll. s | GLB validator | USD mass vs MJCF | repair |\n"
        "|---|---|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---|---:|---|\n"
    )
    lines = [
        f"| {r['scene']} | {r['exact_loads']} | {pct(r['mass_vs_true'])} | {pct(r['inertia_vs_true'])} | {pct(r['mass_vs_twin'])} "
        f"| {pct(r['inertia_vs_twin'])} | {pct(r['vol_cad'])} | {pct(r['vol_twin'])} | {r['col_kind']} | {r['hulls']} | {pct(r['col_err'])} "
        f"| {r['hausdorff_mm']:.2f} | {r['col_s']:.0f} | {r['gltf']} | {pct(r['usd_mass_vs_mjcf'])} | {r['repair']} |"
        for r in rows
    ]
    return head + "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--twins", type=Path, default=REPO.parent / "twins_base", help="directory of twins named by scene")
    ap.add_argument("--only", nargs="*", default=[])
    ap.add_argument("--out", type=Path, default=RESULTS / "twin_physics.md")
    ap.add_argument("--coacd-timeout", type=float, default=1800.0, help="CoACD wall-clock budget per part (s); the product's is 300")
    args = ap.parse_args()
    if not RIG_SCENES.exists():
        raise SystemExit(f"needs the shared data folder {RIG_SCENES}")
    scenes = sorted(p.name for p in (RIG_SCENES / "scenes").iterdir() if (args.twins / p.name / "twin.json").exists())
    scenes = [s for s in scenes if not args.only or s in args.only]
    if not scenes:
        raise SystemExit(f"no twins of rig_scenes scenes in {args.twins}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in scenes:
            rows.append(measure(scene, args.twins / scene, Path(tmp) / scene, DecompositionOptions(timeout_s=args.coacd_timeout)))
            r = rows[-1]
            print(f"{scene}: mass {100 * r['mass_vs_true']:+.1f}% vs true ({100 * r['mass_vs_twin']:+.2f}% vs twin), "
                  f"{r['col_kind']} {r['hulls']} hulls {100 * r['col_err']:+.1f}%, {r['col_s']:.0f} s", flush=True)
            # The table so far after every twin: a long run cut short still leaves its rows.
            table = render_table(rows, f"{load_line()} after the last row")
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(table)
    print(table)


if __name__ == "__main__":
    main()

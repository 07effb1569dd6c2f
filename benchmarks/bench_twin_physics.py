"""Simulation-ready twins against the truth: the rig_scenes twins exported as MuJoCo bodies.

For every scene of ../shared/data/rig_scenes with a twin in --twins (cadsplat twin directories,
one per scene name), at one density (ABS, 1050 kg/m^3; every ratio below is density-free):
- the volume chain, each step against the true volume (gt_mesh.ply; voxel-filled at 1 mm only
  where it is open): the twin's CAD (mesh_cad.glb), its deformed mesh as saved (mesh_deformed.glb)
  and after `repair_mesh`, and MuJoCo's mass / density. The deformed surface's mean signed distance
  inside the true one (the true mesh taken into the twin's object frame through the cameras) times
  its area is the volume the reconstruction's geometry alone accounts for;
- mass and principal inertia MuJoCo computes from the exported MJCF (`inertia="exact"`) against
  density x the true mesh, and against the twin's own repaired mesh (what the exporter can be held to);
- the collision geometry: kind, hulls, volume error, Hausdorff to the twin surface, seconds and their ratio
  to the speed anchor's step read at the start of the run (`x anchor`; `benchmarks._common.machine_reading`,
  its ms, CPU and load in the header);
- the GLB export in the Khronos glTF validator (errors; "n/a" when it is not installed — set
  CADSPLAT_GLTF_VALIDATOR to a directory holding node_modules/gltf-validator; `make env` installs it), and the USD export
  read back by pxr (`check_usd`) with its mass against MuJoCo's.

Frames: the twin's object frame is its CAD's (twin.json `model_id`); gt_mesh.ply is in the frame of
the scene's own CAD variant. The two agree only as far as the registration is right, so the true
mesh is mapped into the twin's frame by the cameras, c2w_twin @ inv(c2w_true) averaged over the
training views (`true_to_twin`); volume and principal moments do not depend on the frame.

    python -m benchmarks.bench_twin_physics --twins DIR [--only SCENE ...] [--coacd-timeout S]

Writes benchmarks/results/twin_physics.md.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh
from pxr import Usd, UsdPhysics
from scipy.spatial.transform import Rotation

from benchmarks._common import REPO, RESULTS, SHARED, MachineReading, gltf_validator, load_line, machine_reading
from reconstruction.mesh_io import read_mesh_parts
from simulation.asset import repair_mesh
from simulation.collision import DecompositionOptions
from simulation.export import export_glb, twin_body
from simulation.mjcf import SimOptions, write_mjcf_package
from simulation.run import SimulationError, load_model
from simulation.usd import write_usd

RIG_SCENES = SHARED / "rig_scenes"
VOXEL_M = 1e-3
OFFSET_SAMPLES = 20_000


def true_solid(mesh: trimesh.Trimesh) -> tuple[float, np.ndarray, str]:
    """(volume m^3, inertia [3, 3] about the centre of mass at unit density, how) of the true mesh:
    exact when it is closed, else its 1 mm voxel filling. Each filled voxel is a point mass plus its
    own cube inertia, and the voxels the surface passes through weigh half: counted whole, the
    surface layer adds about area x pitch / 2 (+6 % to +32 % on the rig_scenes objects, which are
    thin; at half weight +0.1 % to +1.4 %). Refused when the fill leaks through a hole wider than
    the pitch (nothing inside gets filled)."""
    mesh = mesh.copy()
    mesh.merge_vertices()
    if mesh.is_volume:
        return float(mesh.volume), np.asarray(mesh.moment_inertia), "closed mesh"
    surface = mesh.voxelized(VOXEL_M)
    filled = surface.copy().fill()
    if len(filled.points) == len(surface.points):
        raise ValueError(f"the true mesh is open and its {1e3 * VOXEL_M:g} mm voxel fill leaks through a hole")
    on_surface = {tuple(i) for i in surface.sparse_indices.tolist()}
    w = VOXEL_M**3 * np.array([0.5 if tuple(i) in on_surface else 1.0 for i in filled.sparse_indices.tolist()])
    pts = np.asarray(filled.indices_to_points(filled.sparse_indices))
    com = w @ pts / w.sum()
    d = pts - com
    inertia = np.eye(3) * (w * (d * d).sum(1)).sum() - (w[:, None] * d).T @ d + w.sum() * VOXEL_M**2 / 6 * np.eye(3)
    return float(w.sum()), inertia, f"voxels {1e3 * VOXEL_M:g} mm (open mesh; surface voxels at half weight)"


def true_to_twin(twin_json: dict, gt_json: dict, transforms: dict) -> np.ndarray:
    """[4, 4] rigid map from the true object frame to the twin's: per training view
    c2w_twin @ inv(c2w_true) (both OpenCV, matched by image name), rotations averaged (scipy), translations meaned."""
    names = [Path(f["file_path"]).name for f in transforms["frames"]]
    true_c2w = dict(zip(names, np.asarray(gt_json["train"]["c2w_opencv_object"], np.float64)))
    maps = [
        np.asarray(c["c2w_object_opencv"], np.float64) @ np.linalg.inv(true_c2w[Path(c["file_path"]).name]) for c in twin_json["cameras"]
    ]
    out = np.eye(4)
    out[:3, :3] = Rotation.from_matrix([m[:3, :3] for m in maps]).mean().as_matrix()
    out[:3, 3] = np.mean([m[:3, 3] for m in maps], 0)
    return out


def inside_offset(surface: trimesh.Trimesh, true_mesh: trimesh.Trimesh) -> float:
    """Mean signed distance (m) of area-uniform points of `surface` inside `true_mesh` (negative: outside)."""
    pts = trimesh.sample.sample_surface(surface, OFFSET_SAMPLES, seed=0)[0]
    return float(trimesh.proximity.signed_distance(true_mesh, pts).mean())


def pushed_out(mesh: trimesh.Trimesh, distance: float) -> trimesh.Trimesh:
    """`mesh` with every vertex moved `distance` (m) along its normal: the surface without a uniform inward bias."""
    return trimesh.Trimesh(mesh.vertices + distance * mesh.vertex_normals, mesh.faces, process=False)


def closed_volume(path: Path) -> float:
    """Volume (m^3) of a mesh file after `repair_mesh`."""
    parts = read_mesh_parts(path)
    v, f, _, _ = repair_mesh(parts.vertices, parts.faces)
    return float(trimesh.Trimesh(v, f, process=False).volume)


def worst(deviation: np.ndarray) -> float:
    """The signed deviation of largest magnitude (principal moments compared in ascending order)."""
    return float(deviation[np.argmax(np.abs(deviation))])


def gltf_errors(glb: Path) -> str:
    """Error count of the Khronos glTF validator on `glb`, or "n/a" when node or the validator is absent."""
    found = gltf_validator()
    if found is None:
        return "n/a"
    node, mods = found
    js = (
        "const fs=require('fs');require('gltf-validator').validateBytes(new Uint8Array(fs.readFileSync(process.argv[1])))"
        ".then(r=>console.log(JSON.stringify(r.issues)))"
    )
    res = subprocess.run(
        [node, "-e", js, str(glb)], capture_output=True, text=True, env={**os.environ, "NODE_PATH": str(mods)}, timeout=300
    )
    if res.returncode != 0:
        return "failed"
    issues = json.loads(res.stdout)
    return f"{issues['numErrors']} err / {issues['numWarnings']} warn"


def measure(scene: str, twin_dir: Path, work: Path, decomposition: DecompositionOptions) -> dict:
    scene_dir = RIG_SCENES / "scenes" / scene
    twin_json = json.loads((twin_dir / "twin.json").read_text())
    gt_json = json.loads((scene_dir / "gt.json").read_text())
    true_mesh = trimesh.load(scene_dir / "gt_mesh.ply", process=False)
    v_true, i_true, how = true_solid(true_mesh)
    t0 = time.perf_counter()
    body = twin_body(twin_dir, decomposition=decomposition)
    export_s = time.perf_counter() - t0
    a, col = body.asset, body.collision
    rho = a.density.value
    row = {
        "scene": scene,
        "model": twin_json["model_id"],
        "true_model": gt_json["model_id"],
        "repair": "; ".join(a.repair.summary()),
        "export_s": export_s,
        "v_true": v_true,
        "true_from": how,
    }
    try:
        model = load_model(write_mjcf_package(work / "mjcf", [body], SimOptions()))
        row["exact_loads"] = "yes"
        mj_mass, mj_inertia = float(model.body_mass[1]), np.sort(model.body_inertia[1])
    except SimulationError as e:
        row["exact_loads"] = f"no: {e}"
        mj_mass, mj_inertia = np.nan, np.full(3, np.nan)
    true_moments = np.sort(np.linalg.eigvalsh(rho * i_true))
    in_twin = true_mesh.copy().apply_transform(
        true_to_twin(twin_json, gt_json, json.loads((scene_dir / "train" / "transforms.json").read_text()))
    )
    offset = inside_offset(a.trimesh(), in_twin)
    row.update(
        vol_cad=closed_volume(twin_dir / "mesh_cad.glb") / v_true - 1,
        vol_raw=a.repair.volume_before / v_true - 1,
        vol_repaired=a.mass.volume / v_true - 1,
        vol_mjcf=mj_mass / rho / v_true - 1,
        offset_mm=1e3 * offset,
        vol_offset=-a.trimesh().area * offset / v_true,
        vol_unbiased=pushed_out(a.trimesh(), offset).volume / v_true - 1,
        mass_vs_true=mj_mass / (rho * v_true) - 1,
        inertia_vs_true=worst(mj_inertia / true_moments - 1),
        gyration_vs_true=worst((mj_inertia / mj_mass) / (true_moments / (rho * v_true)) - 1),
        mass_vs_twin=mj_mass / a.mass.mass - 1,
        inertia_vs_twin=worst(mj_inertia / np.sort(a.mass.principal_moments) - 1),
        col_kind=col.kind,
        hulls=col.hull_count,
        col_err=col.volume_error,
        hausdorff_mm=1e3 * col.hausdorff,
        col_s=col.seconds,
    )
    glb = export_glb(twin_dir, work / "twin.glb")
    row["gltf"] = gltf_errors(glb)
    usd = write_usd(work / "twin.usda", body)  # raises UsdCheckError unless pxr reads it back as the body
    stage = Usd.Stage.Open(str(usd))  # held: its prims live only as long as the stage
    row["usd_mass_vs_mjcf"] = UsdPhysics.MassAPI(stage.GetDefaultPrim()).GetMassAttr().Get() / mj_mass - 1
    return row


def pct(x: float) -> str:
    return "n/a" if not np.isfinite(x) else f"{100 * x:+.1f}%"


def render_table(rows: list[dict], machine: MachineReading, load_at_end: str) -> str:
    head = (
        "# Twins as simulation bodies: mass, inertia and contact geometry against the truth\n\n"
        f"rig_scenes twins (cadsplat twin directories), exported with `simulation.export.twin_body` at 1050 kg/m^3; "
        f'mass and principal inertia as MuJoCo computes them from the MJCF (`inertia="exact"`). '
        f"{machine.header()} {load_at_end}.\n\n"
        "## Where the volume goes\n\n"
        "Each step's enclosed volume against the true one (gt_mesh.ply). *CAD*: the twin's mesh_cad.glb after repair; "
        "*deformed*: mesh_deformed.glb as saved (signed volume of the welded mesh), then after `repair_mesh`; *MJCF*: MuJoCo's mass / density. "
        "*offset*: mean signed distance of the repaired deformed surface inside the true surface (true mesh in the twin's frame); "
        "*area x offset*: the volume that offset alone removes (first order), as a share of the true volume; *rest*: repaired less that; "
        "*pushed out*: the repaired mesh with every vertex moved out along its normal by the offset (the twin's volume were the bias gone).\n\n"
        "| scene | twin's CAD | true V cm^3 (from) | CAD | deformed | repaired | MJCF | offset mm | area x offset | rest | pushed out |\n"
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    )
    chain = [
        f"| {r['scene']} | {r['model'] if r['model'] == r['true_model'] else r['model'] + ' (wrong model)'} | {1e6 * r['v_true']:.2f} ({r['true_from']}) "
        f"| {pct(r['vol_cad'])} | {pct(r['vol_raw'])} | {pct(r['vol_repaired'])} | {pct(r['vol_mjcf'])} | {r['offset_mm']:+.2f} "
        f"| {pct(r['vol_offset'])} | {pct(r['vol_repaired'] - r['vol_offset'])} | {pct(r['vol_unbiased'])} |"
        for r in rows
    ]
    physics = (
        "\n\n## Physics export\n\n"
        "- *vs true*: against density x the true mesh; acceptance 3 % mass, 5 % inertia (inertia: the principal moment, ascending "
        "order, furthest off, with its sign). *gyration*: inertia / mass against the true one's: the shape's share of the inertia error.\n"
        "- *vs twin*: against the twin's own repaired mesh: what the exporter computes (exactness of the physics export).\n"
        "- collision: chosen at 10 % volume tolerance; Hausdorff between the collision set's surface and the twin mesh's.\n\n"
        "| scene | exact loads | mass vs true | inertia vs true | gyration vs true | mass vs twin | inertia vs twin "
        "| collision | hulls | coll. vol err | Hausdorff mm | coll. s | x anchor | GLB validator | USD mass vs MJCF | repair |\n"
        "|---|---|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---|---:|---|\n"
    )
    lines = [
        f"| {r['scene']} | {r['exact_loads']} | {pct(r['mass_vs_true'])} | {pct(r['inertia_vs_true'])} | {pct(r['gyration_vs_true'])} "
        f"| {pct(r['mass_vs_twin'])} | {pct(r['inertia_vs_twin'])} | {r['col_kind']} | {r['hulls']} | {pct(r['col_err'])} "
        f"| {r['hausdorff_mm']:.2f} | {r['col_s']:.0f} | {machine.x_anchor(r['col_s'])} | {r['gltf']} | {pct(r['usd_mass_vs_mjcf'])} | {r['repair']} |"
        for r in rows
    ]
    return head + "\n".join(chain) + physics + "\n".join(lines) + "\n"


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
    machine = machine_reading()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in scenes:
            rows.append(measure(scene, args.twins / scene, Path(tmp) / scene, DecompositionOptions(timeout_s=args.coacd_timeout)))
            r = rows[-1]
            print(
                f"{scene}: mass {100 * r['mass_vs_true']:+.1f}% vs true ({100 * r['mass_vs_twin']:+.2f}% vs twin), offset {r['offset_mm']:+.2f} mm, "
                f"{r['col_kind']} {r['hulls']} hulls {100 * r['col_err']:+.1f}%, {r['col_s']:.0f} s",
                flush=True,
            )
            # The table so far after every twin: a long run cut short still leaves its rows.
            table = render_table(rows, machine, f"{load_line()} after the last row")
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(table)
    print(table)


if __name__ == "__main__":
    main()

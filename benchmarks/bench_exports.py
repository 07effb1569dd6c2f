"""The twin's appearance in other tools' formats, on the rig_scenes twins (issue 59's acceptance).

For every scene of ../shared/data/rig_scenes with a twin in --twins (one cadsplat twin directory per
scene name), up given as the CAD's declared axis (gt.json `object.up_axis`, "z"; the scenes' rig frame
is their first camera's, so no single rig.toml up fits them all):
- USD: the file pxr reads back (`write_usd` checks it through UsdVol's schema before renaming it into
  place): its splat count against the twin's, its mass against the one MuJoCo compiles from the MJCF
  of the same body, its upAxis;
- up: the angle between that up and the cameras' mean up axis (they are mounted upright around the
  conveyor) taken into the object frame by the twin's registration;
- GLB (KHR_gaussian_splatting, mesh alongside): the Khronos validator's errors, and those left once
  the ones it raises only for not knowing the extension's attribute names are set aside (its released
  version has no support for extension-defined semantics: KhronosGroup/glTF-Validator issue 252);
- .spz: its size against the PLY's;
- collision: hulls against the budget, the volume error left at the budget, seconds.

    python -m benchmarks.bench_exports --twins DIR [--only SCENE ...] [--hull-budget 32] [--coacd-timeout S]

Writes benchmarks/results/exports.md.
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

from benchmarks._common import RESULTS, SHARED, gltf_validator, load_line
from reconstruction.twin import SPLATS_PLY, load_twin
from simulation.collision import DEFAULT_HULL_BUDGET, DecompositionOptions
from simulation.export import export_glb, export_spz, twin_body, twin_up
from simulation.mjcf import SimOptions, write_mjcf_package
from simulation.run import load_model
from simulation.usd import write_usd

RIG_SCENES = SHARED / "rig_scenes"


def validator_errors(glb: Path) -> tuple[str, str, str]:
    """(all errors, errors beyond the unknown extension's attribute names, warnings) of the Khronos
    validator on `glb`; "n/a" when it is not installed."""
    found = gltf_validator()
    if found is None:
        return "n/a", "n/a", "n/a"
    node, mods = found
    js = (
        "const fs=require('fs');require('gltf-validator').validateBytes(new Uint8Array(fs.readFileSync(process.argv[1])))"
        ".then(r=>console.log(JSON.stringify(r.issues)))"
    )
    res = subprocess.run(
        [node, "-e", js, str(glb)], capture_output=True, text=True, env={**os.environ, "NODE_PATH": str(mods)}, timeout=600
    )
    issues = json.loads(res.stdout)
    beyond = [
        m
        for m in issues["messages"]
        if m["severity"] == 0
        and not (m["code"] == "MESH_PRIMITIVE_INVALID_ATTRIBUTE" and m["pointer"].rsplit("/", 1)[-1].startswith("KHR_gaussian_splatting:"))
    ]
    return str(issues["numErrors"]), str(len(beyond)), str(issues["numWarnings"])


def cameras_up(scene: str) -> np.ndarray:
    """The rig cameras' mean up axis [3] in the rig frame (nerfstudio c2w: the camera's +y is up)."""
    frames = json.loads((RIG_SCENES / "scenes" / scene / "train" / "transforms.json").read_text())["frames"]
    u = np.sum([np.asarray(f["transform_matrix"], np.float64)[:3, 1] for f in frames], 0)
    return u / np.linalg.norm(u)


def measure(scene: str, twin_dir: Path, work: Path, decomposition: DecompositionOptions) -> dict:
    from pxr import Usd, UsdGeom, UsdPhysics, UsdVol

    gt = json.loads((RIG_SCENES / "scenes" / scene / "gt.json").read_text())
    twin = load_twin(twin_dir)
    cad_up_axis = gt["object"]["up_axis"]
    up = twin_up(twin, cad_up_axis=cad_up_axis)
    seen_up = twin.sim3_rig_to_object.rotation @ cameras_up(scene)
    t0 = time.perf_counter()
    body = twin_body(twin_dir, twin=twin, up=up, decomposition=decomposition)
    body_s = time.perf_counter() - t0
    model = load_model(write_mjcf_package(work / "mjcf", [body], SimOptions()))
    usd = write_usd(work / f"{scene}.usdc", body, twin.gaussians, up)
    stage = Usd.Stage.Open(str(usd))  # held: its prims live only as long as the stage
    root = stage.GetDefaultPrim()
    field = UsdVol.ParticleField3DGaussianSplat(root.GetChild("splats"))
    glb = export_glb(twin_dir, work / f"{scene}.glb", mesh=True, cad_up_axis=cad_up_axis)
    spz = export_spz(twin_dir, work / f"{scene}.spz", cad_up_axis=cad_up_axis)
    errors, beyond, warnings = validator_errors(glb)
    col = body.collision
    return dict(
        scene=scene,
        splats=twin.num_splats,
        sh=twin.gaussians.sh_degree,
        usd_splats=len(field.GetPositionsAttr().Get()),
        usd_mass_vs_mjcf=UsdPhysics.MassAPI(root).GetMassAttr().Get() / float(model.body_mass[1]) - 1,
        up_axis=UsdGeom.GetStageUpAxis(stage),
        up_err_deg=float(np.degrees(np.arccos(np.clip(up.vector @ seen_up, -1, 1)))),
        glb_errors=errors,
        glb_beyond=beyond,
        glb_warnings=warnings,
        glb_kb=glb.stat().st_size / 1024,
        spz_kb=spz.stat().st_size / 1024,
        ply_kb=(twin_dir / SPLATS_PLY).stat().st_size / 1024,
        hulls=col.hull_count + len(col.primitives),
        budget=col.hull_budget,
        col_kind=col.kind,
        col_err=col.volume_error,
        body_s=body_s,
    )


def render_table(rows: list[dict], budget: int, load: str) -> str:
    lines = [
        "# Exports of the rig_scenes twins: USD, glTF KHR_gaussian_splatting, .spz, collision at the hull budget",
        "",
        f'`python -m benchmarks.bench_exports` (hull budget {budget}); {load}. Up: the CAD\'s declared axis (+z); "up err" is its',
        "angle to the cameras' mean up axis taken into the object frame by the twin's registration. GLB errors: all of the Khronos validator's (2.0.0-dev.3.10), then those left beyond the ones it raises for",
        "every `KHR_gaussian_splatting:*` attribute name, which its released version does not accept yet (KhronosGroup/glTF-Validator#252).",
        "",
        "| scene | splats | SH | USD splats | USD mass vs MJCF | upAxis | up err deg | GLB errors (all / beyond) | GLB warn | GLB KiB | PLY KiB | spz KiB | PLY/spz | hulls / budget | collision | vol err at budget | body s |",
        "|---|---:|---:|---:|---:|---|---:|---|---:|---:|---:|---:|---:|---:|---|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['splats']} | {r['sh']} | {r['usd_splats']} | {100 * r['usd_mass_vs_mjcf']:+.4f}% | {r['up_axis']} | {r['up_err_deg']:.2f} | "
            f"{r['glb_errors']} / {r['glb_beyond']} | {r['glb_warnings']} | {r['glb_kb']:.0f} | {r['ply_kb']:.0f} | {r['spz_kb']:.0f} | {r['ply_kb'] / r['spz_kb']:.1f} | "
            f"{r['hulls']} / {r['budget']} | {r['col_kind']} | {100 * r['col_err']:+.1f}% | {r['body_s']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--twins", type=Path, required=True, help="directory of twin directories named after the scenes")
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--hull-budget", type=int, default=DEFAULT_HULL_BUDGET)
    ap.add_argument("--coacd-timeout", type=float, default=300.0)
    ap.add_argument("--out", type=Path, default=RESULTS / "exports.md")
    args = ap.parse_args()
    load = load_line()
    decomposition = DecompositionOptions(hull_budget=args.hull_budget, timeout_s=args.coacd_timeout)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for twin_dir in sorted(p for p in args.twins.iterdir() if (p / "twin.json").exists()):
            if args.only and twin_dir.name not in args.only:
                continue
            work = Path(tmp) / twin_dir.name
            work.mkdir()
            rows.append(measure(twin_dir.name, twin_dir, work, decomposition))
            print(render_table(rows[-1:], args.hull_budget, load).splitlines()[-1], flush=True)
    text = render_table(rows, args.hull_budget, load)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()

"""Regenerate the bundled sample (`sample/`) from the shared YCB scans and CAD parts.

    python -m benchmarks.bench_make_sample [--shared ../shared/data] [--force]

What it makes (all deterministic):
  sample/object/           the physical object: YCB 050_medium_clamp's scan (OBJ as published,
                           texture downscaled to 1024 px JPEG)
  sample/train, heldout,   `cadsplat synth sample/object/textured.obj --views 9 --heldout 36
  sample/gt.json           --size 320x240 --seed 7` (the synthetic rig's captures and truth)
  sample/library_meshes/   the CAD library, metres: the clamp as a CAD variant (decimated to
                           2.5k faces + a smooth few-mm deformation) and four distractors
  sample/sample.json       which library model is the right one, how each mesh was made
The new sample is assembled beside the old one and swapped in only when complete. Prints a one-row table:
the synthesis wall time beside its ratio to the speed anchor's step read at the start of the run (`x anchor`;
`benchmarks._common.machine_reading`, whose ms, CPU and load head the table), and the size on disk.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import fast_simplification
import numpy as np
import trimesh

from benchmarks._common import REPO, SHARED, MachineReading, machine_reading
from calibration.fileio import atomic_write_bytes, atomic_write_json, sha256_file
from calibration.units import UNIT_TO_M
from reconstruction.mesh_io import read_mesh_parts
from rig.synthetic import synth_dataset

OBJECT = "050_medium_clamp"
TRUE_MODEL_ID = "medium_clamp_cad"
SEED = 7
DEFORM_AMPLITUDE_M = 0.003
# Library distractors: (id, source under shared data, unit of the source file, target faces).
DISTRACTORS = [
    ("phillips_screwdriver", "objects/ycb/043_phillips_screwdriver/textured.obj", "m", 2500),
    ("scissors", "objects/ycb/037_scissors/textured.obj", "m", 2500),
    ("imu_adis16480", "cad/parts/ADIS16480.STL", "m", 2500),
    ("idler_riser", "cad/parts/idler_riser.STL", "in", 2500),
]


def welded(path: Path, unit: str) -> trimesh.Trimesh:
    """Geometry only, seams welded (UV seams split vertices), in metres, frame untouched."""
    parts = read_mesh_parts(path)
    out = trimesh.Trimesh(parts.vertices * UNIT_TO_M[unit], parts.faces, process=True)
    out.merge_vertices()
    return out


def decimate(mesh: trimesh.Trimesh, faces: int) -> trimesh.Trimesh:
    if len(mesh.faces) <= faces:
        return mesh
    v, f = fast_simplification.simplify(
        np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64), target_reduction=1.0 - faces / len(mesh.faces)
    )
    return trimesh.Trimesh(v, f, process=True)


def smooth_deformation(points: np.ndarray, extent: np.ndarray, amplitude: float, seed: int) -> np.ndarray:
    """Displacements [N, 3]: three sinusoids with wavelengths of about the object's size (a bent, bulged CAD variant)."""
    rng = np.random.default_rng(seed)
    out = np.zeros_like(points)
    centre = points.mean(0)
    for axis in range(3):
        k = rng.normal(size=3)
        k *= 2 * np.pi / (1.2 * extent.max() * np.linalg.norm(k))
        phase = rng.uniform(0, 2 * np.pi)
        out[:, axis] = np.sin((points - centre) @ k + phase)
    return amplitude * out / np.linalg.norm(out, axis=1).max()


def write_object(shared: Path, dst: Path) -> None:
    src = shared / "objects" / "ycb" / OBJECT
    dst.mkdir(parents=True)
    shutil.copyfile(src / "textured.obj", dst / f"{OBJECT}.obj")  # its mtllib line still names textured.mtl
    (dst / "textured.mtl").write_text("newmtl material_0\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nmap_Kd texture_map.jpg\n")
    tex = cv2.imread(str(src / "texture_map.png"), cv2.IMREAD_COLOR)
    tex = cv2.resize(tex, (1024, 1024), interpolation=cv2.INTER_AREA)
    ok, jpg = cv2.imencode(".jpg", tex, [cv2.IMWRITE_JPEG_QUALITY, 92])
    atomic_write_bytes(dst / "texture_map.jpg", jpg.tobytes())


def write_library(shared: Path, dst: Path) -> list[dict]:
    dst.mkdir(parents=True)
    models = []
    clamp = welded(shared / "objects" / "ycb" / OBJECT / "textured.obj", "m")
    cad = decimate(clamp, 2500)
    disp = smooth_deformation(cad.vertices, cad.extents, DEFORM_AMPLITUDE_M, SEED)
    cad = trimesh.Trimesh(cad.vertices + disp, cad.faces, process=False)
    cad.export(dst / f"{TRUE_MODEL_ID}.ply")
    models.append(
        {
            "id": TRUE_MODEL_ID,
            "file": f"library_meshes/{TRUE_MODEL_ID}.ply",
            "unit": "m",
            "faces": len(cad.faces),
            "source": f"YCB {OBJECT} google_16k",
            "made": f"decimated {len(clamp.faces)} -> {len(cad.faces)} faces, smooth deformation up to {DEFORM_AMPLITUDE_M * 1e3:.1f} mm",
            "max_deformation_mm": float(np.linalg.norm(disp, axis=1).max() * 1e3),
            "is_true_object": True,
        }
    )
    for model_id, rel, unit, faces in DISTRACTORS:
        mesh = decimate(welded(shared / rel, unit), faces)
        mesh.export(dst / f"{model_id}.ply")
        models.append(
            {
                "id": model_id,
                "file": f"library_meshes/{model_id}.ply",
                "unit": "m",
                "faces": len(mesh.faces),
                "source": rel,
                "made": (f"converted from {unit} to m, " if unit != "m" else "") + f"decimated to {len(mesh.faces)} faces",
                "is_true_object": False,
            }
        )
    return models


README = """# The bundled sample

A small synthetic capture of a real scanned object and a small CAD library, used by `cadsplat demo`
(and its tests) so a fresh clone works without `../shared`. Regenerate with
`python -m benchmarks.bench_make_sample --force` (needs `../shared/data`).

- `object/`: the "physical" object, YCB **050_medium_clamp** (google_16k scan, metres). Texture
  downscaled to 1024 px.
- `train/` (9 views, 320x240, masks, empty-rig backgrounds, poses in the rig frame), `heldout/`
  (36-view orbit at three elevations), `gt.json` (the rig->object Sim(3) and true object-frame
  poses): made by the synthetic rig, `cadsplat synth object/050_medium_clamp.obj --views 9 --heldout 36
  --size 320x240 --seed 7` (MuJoCo renderer).
- `library_meshes/` (PLY, metres): `medium_clamp_cad` is the right model, as a CAD variant
  (decimated to 2.5k faces and smoothly deformed by up to 3 mm); distractors: YCB
  043_phillips_screwdriver and 037_scissors (decimated), and trimesh's CAD test parts
  ADIS16480 (metres) and idler_riser (inches, converted to metres).
- `sample.json`: which model is the right one and how each file was made.

## Credits
- YCB object models: Calli et al., "The YCB Object and Model Set", https://www.ycbbenchmarks.com/ —
  licensed under CC BY 4.0 (scans, textures and the derived decimated/deformed meshes here).
- CAD parts ADIS16480 and idler_riser: trimesh's test models (https://github.com/mikedh/trimesh),
  MIT licence.
"""


def build(shared: Path, dst: Path) -> dict:
    t0 = time.perf_counter()
    write_object(shared, dst / "object")
    gt = synth_dataset(dst / "object" / f"{OBJECT}.obj", dst, views=9, heldout=36, size=(320, 240), seed=SEED)
    synth_s = time.perf_counter() - t0
    models = write_library(shared, dst / "library_meshes")
    (dst / "README.md").write_text(README)
    manifest = {
        "format": "cadsplat-sample/1",
        "object": OBJECT,
        "mesh": f"object/{OBJECT}.obj",
        "true_model_id": TRUE_MODEL_ID,
        "train": "train",
        "heldout": "heldout",
        "gt": "gt.json",
        "library_meshes": "library_meshes",
        "models": models,
        "sha256": {
            str(p.relative_to(dst)): sha256_file(p) for p in sorted((dst / "library_meshes").iterdir()) + sorted((dst / "object").iterdir())
        },
    }
    atomic_write_json(dst / "sample.json", manifest)
    return {"synth_s": synth_s, "views": gt["views"], "heldout": gt["heldout"]}


def summary_table(stats: dict, size_bytes: int, machine: MachineReading) -> str:
    """The sample's one-row table under the machine reading it was timed against."""
    return (
        f"{machine.header()}\n\n| sample | views | held-out | synth wall (s) | x anchor | size on disk (MB) |\n|---|---|---|---|---|---|\n"
        f"| {OBJECT} | {stats['views']} | {stats['heldout']} | {stats['synth_s']:.1f} | {machine.x_anchor(stats['synth_s'])} "
        f"| {size_bytes / 1e6:.2f} |"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shared", type=Path, default=SHARED)
    ap.add_argument("--out", type=Path, default=REPO / "sample")
    ap.add_argument("--force", action="store_true", help="replace an existing sample")
    args = ap.parse_args()
    if not (args.shared / "objects" / "ycb" / OBJECT).is_dir():
        print(f"error: {args.shared} has no objects/ycb/{OBJECT}; pass --shared", file=sys.stderr)
        return 2
    if args.out.exists() and not args.force:
        print(f"error: {args.out} exists; pass --force to replace it", file=sys.stderr)
        return 2
    machine = machine_reading()
    tmp = Path(tempfile.mkdtemp(prefix=".sample.", dir=args.out.parent))
    try:
        stats = build(args.shared, tmp / "sample")
        if args.out.exists():
            old = args.out.with_name(args.out.name + ".old")
            args.out.rename(old)
            (tmp / "sample").rename(args.out)
            shutil.rmtree(old)
        else:
            (tmp / "sample").rename(args.out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    size = sum(p.stat().st_size for p in args.out.rglob("*") if p.is_file())
    print(summary_table(stats, size, machine))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""A part with a known dent: does `cadsplat inspect` FAIL it at the right place and PASS the undented part?

    python -m benchmarks.bench_dent [--preset preview] [--depth-mm 2] [--radius-mm 8] [--tolerance 1.5] [--work DIR]
        [--part OBJ]

The bundled sample's object (YCB medium clamp, sample/object, metres; `--part`: another textured OBJ in metres, e.g.
a shared YCB scan) is the nominal part and its own CAD model (a library of that one mesh). A patch of it, centred on the side-wall vertex the synthetic
rig's cameras see most, is pushed inwards along the surface normal by up to `depth` (a cosine bump
of `radius`). Both parts are photographed by the synthetic rig (`cadsplat synth`: 9 views, 320x240,
the same cameras and pose), reconstructed against the nominal CAD with `preset`, and inspected at
`tolerance`. Writes benchmarks/results/dent_<preset>.md: the verdicts, then the wall times, each with its
ratio to the speed anchor's step read at the start of the run (`benchmarks._common.machine_reading`;
the anchor ms, CPU and load stated there); the dated sections written by hand below are kept. Needs no shared data.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from benchmarks._common import REPO, RESULTS, MachineReading, load_line, machine_reading, write_results

SOURCE = REPO / "sample" / "object" / "050_medium_clamp.obj"


def read_obj_positions(text: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertex positions [V, 3] and triangle position indices [F, 3] (0-based) of an OBJ's text."""
    verts, faces = [], []
    for line in text.splitlines():
        if line.startswith("v "):
            verts.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("f "):
            idx = [int(tok.split("/")[0]) - 1 for tok in line.split()[1:]]
            faces += [[idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1)]
    return np.array(verts, np.float64), np.array(faces, np.int64)


def write_obj_positions(text: str, vertices: np.ndarray) -> str:
    """`text` with its `v` lines replaced by `vertices` [V, 3] in order, and its stored normals dropped
    (`vn` lines and the face's normal indices): whoever renders it recomputes them from the new shape."""
    out, k = [], 0
    for line in text.splitlines():
        if line.startswith("v "):
            x, y, z = vertices[k]
            out.append(f"v {x:.7f} {y:.7f} {z:.7f}")
            k += 1
        elif line.startswith("vn "):
            continue
        elif line.startswith("f "):
            out.append("f " + " ".join("/".join(tok.split("/")[:2]) for tok in line.split()[1:]))
        else:
            out.append(line)
    return "\n".join(out) + "\n"


def dent(vertices: np.ndarray, faces: np.ndarray, centre: np.ndarray, depth: float, radius: float) -> np.ndarray:
    """`vertices` [V, 3] with a dent: pushed against their outward normal by depth * (1 + cos(pi d / radius)) / 2
    within `radius` of `centre` [3] (d: straight-line distance), unmoved beyond. Units of the mesh."""
    from reconstruction.inspect import vertex_normals

    v = np.asarray(vertices, np.float64)
    # Texture seams duplicate positions: weld them for the normals so a seam does not tear open.
    uniq, inverse = np.unique(v, axis=0, return_inverse=True)
    normals = vertex_normals(uniq, inverse.reshape(-1)[faces])[inverse.reshape(-1)]
    d = np.linalg.norm(v - centre, axis=1)
    push = np.where(d < radius, 0.5 * depth * (1.0 + np.cos(np.pi * np.minimum(d / radius, 1.0))), 0.0)
    return v - push[:, None] * normals


def copy_part(source: Path, text: str, vertices: np.ndarray, out_dir: Path) -> Path:
    """The source OBJ with new positions, beside a copy of the other files of its folder (material, texture)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for path in source.parent.iterdir():
        if path.is_file() and path.suffix.lower() != ".obj":
            shutil.copy(path, out_dir / path.name)
    path = out_dir / source.name
    path.write_text(write_obj_positions(text, vertices))
    return path


def pick_dent_centre(vertices: np.ndarray, faces: np.ndarray, cameras) -> int:
    """The side-wall vertex (normal within 20 deg of horizontal) seen by most cameras, most frontally."""
    from reconstruction.inspect import point_visibility, vertex_normals

    uniq, inverse = np.unique(vertices, axis=0, return_inverse=True)
    f = inverse.reshape(-1)[faces]
    n = vertex_normals(uniq, f)
    vis = point_visibility(uniq, n, uniq, f, cameras)
    score = vis.views - np.nan_to_num(vis.best_angle_deg, nan=90.0) / 90.0
    score[np.abs(n[:, 2]) > np.sin(np.radians(20.0))] = -np.inf
    return int(np.flatnonzero(np.all(vertices == uniq[int(np.argmax(score))], axis=1))[0])


def run(
    work: Path,
    *,
    preset: str,
    depth_mm: float,
    radius_mm: float,
    tolerance_mm: float,
    max_unseen_pct: float,
    views: int = 9,
    seed: int = 7,
    source: Path = SOURCE,
    log=print,
) -> dict:
    """Synthesise, reconstruct and inspect the nominal and the dented part under `work`; returns the findings."""
    import trimesh

    from calibration.camera import Camera
    from deploy.inspection_report import inspect_twin_dir
    from reconstruction.library import build_library
    from reconstruction.pipeline import reconstruct_capture
    from rig.synthetic import synth_dataset

    text = source.read_text()
    model_id = source.parent.name if source.stem == "textured" else source.stem
    vertices, faces = read_obj_positions(text)
    nominal = copy_part(source, text, vertices, work / "nominal" / "object")
    t = time.perf_counter()
    meshes = work / "library_meshes"
    meshes.mkdir(parents=True, exist_ok=True)
    welded = trimesh.Trimesh(vertices, faces, process=True)
    welded.export(meshes / f"{model_id}.ply")
    library = work / "library"
    build_library(meshes, library, progress=False, log=lambda *_: None)
    gt = synth_dataset(nominal, work / "nominal", views=views, heldout=0, seed=seed)
    K = np.array(gt["train_intrinsics"][0])
    w, h = gt["size"]
    cams = [Camera(K, w, h, np.zeros(0), np.array(c)) for c in gt["train_c2w_object"]]
    centre_index = pick_dent_centre(vertices, faces, cams)
    centre = vertices[centre_index]
    dented_path = copy_part(source, text, dent(vertices, faces, centre, depth_mm * 1e-3, radius_mm * 1e-3), work / "dented" / "object")
    synth_dataset(dented_path, work / "dented", views=views, heldout=0, seed=seed)
    timings = {"synth_and_library_s": time.perf_counter() - t}
    out: dict = {
        "part": str(source),
        "model_id": model_id,
        "dent_centre_mm": (centre * 1000).tolist(),
        "depth_mm": depth_mm,
        "radius_mm": radius_mm,
        "preset": preset,
        "tolerance_mm": tolerance_mm,
        "max_unseen_pct": max_unseen_pct,
        "views": views,
    }
    for name in ("nominal", "dented"):
        t = time.perf_counter()
        log(f"reconstructing the {name} part ({preset})")
        reconstruct_capture(work / name / "train", library, work / name / "twin", preset=preset, model_id=model_id, seed=0, overwrite=True)
        timings[f"reconstruct_{name}_s"] = time.perf_counter() - t
        doc = inspect_twin_dir(
            work / name / "twin", work / name / "inspection", tolerance_mm=tolerance_mm, max_unseen_pct=max_unseen_pct, turntable=8
        )
        v = doc["verdict"]
        out[name] = {
            "line": v["line"],
            "status": v["status"],
            "exit_code": v["exit_code"],
            "unseen_pct": v["unseen_pct"],
            "max_abs_mm": v["max_abs_mm"],
            "at_mm": v["at_mm"],
        }
        if v["at_mm"] is not None:
            out[name]["distance_to_dent_mm"] = float(np.linalg.norm(np.array(v["at_mm"]) - centre * 1000))
        csv_rows = _rows(work / name / "inspection")
        near = np.linalg.norm(csv_rows[:, :3] - centre * 1000, axis=1) < 0.5 * radius_mm
        out[name]["patch_mean_deviation_mm"] = float(np.nanmean(csv_rows[near, 3])) if near.any() else None
        out[name]["patch_seen_vertices"] = int((near & np.isfinite(csv_rows[:, 3])).sum())
        far = np.linalg.norm(csv_rows[:, :3] - centre * 1000, axis=1) > 2 * radius_mm
        out[name]["max_abs_away_from_dent_mm"] = float(np.nanmax(np.abs(csv_rows[far, 3])))
    out["timings_s"] = timings
    return out


def _rows(report: Path) -> np.ndarray:
    """[V, 4] x, y, z, deviation (mm; NaN unseen) from every part CSV of an inspection report."""
    import csv

    rows = []
    for path in sorted((report / "parts").glob("*.csv")):
        for r in csv.DictReader(path.open()):
            dev = float(r["deviation_mm"]) if r["status"] != "unseen" else np.nan
            rows.append([float(r["x_mm"]), float(r["y_mm"]), float(r["z_mm"]), dev])
    return np.array(rows)


def write_markdown(res: dict, machine: MachineReading, load_at_end: str, path: Path) -> str:
    def row(name):
        r = res[name]
        dist = f"{r['distance_to_dent_mm']:.1f}" if r.get("distance_to_dent_mm") is not None else "n/a"
        patch = f"{r['patch_mean_deviation_mm']:+.2f}" if r["patch_mean_deviation_mm"] is not None else "n/a"
        return (
            f"| {name} | `{r['line']}` | {r['exit_code']} | {dist} | {patch} ({r['patch_seen_vertices']} seen) | "
            f"{r['max_abs_away_from_dent_mm']:.2f} | {r['unseen_pct']:.1f} |"
        )

    c = res["dent_centre_mm"]
    t = res["timings_s"]
    text = "\n".join(
        [
            "# Known dent: `cadsplat inspect` on a synthetic part",
            "",
            f"Written {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC by `python -m benchmarks.bench_dent`; {load_at_end} at the end.",
            "",
            (
                "Nominal part and CAD: the bundled sample's YCB medium clamp (sample/object, its own full-resolution mesh as the"
                if Path(res["part"]) == SOURCE
                else f"Nominal part and CAD: `{res['model_id']}` ({res['part']}, its own mesh as the"
            ),
            f"library model). Dented part: the same mesh pushed in along its normal by up to {res['depth_mm']:g} mm (cosine bump,",
            f"radius {res['radius_mm']:g} mm) at ({c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f}) mm, the side-wall vertex the rig sees best.",
            f"Synthetic rig (`cadsplat synth`, {res['views']} views, 320x240, seed 7, same cameras and pose for both); reconstruction",
            f"preset `{res['preset']}` with the model given; `inspect --tolerance {res['tolerance_mm']:g} --max-unseen "
            f"{res['max_unseen_pct']:g}`.",
            "",
            "| part | verdict | exit | worst vertex to dent centre (mm) | mean deviation within r/2 of the centre (mm) | "
            "max abs deviation > 2r from the dent (mm) | unseen % |",
            "|---|---|---:|---:|---:|---:|---:|",
            row("nominal"),
            row("dented"),
            "",
            f"Wall time (x anchor): synthesis + library {t['synth_and_library_s']:.0f} s ({machine.x_anchor(t['synth_and_library_s'])}), "
            f"reconstruction {t['reconstruct_nominal_s']:.0f} s ({machine.x_anchor(t['reconstruct_nominal_s'])}) (nominal) and "
            f"{t['reconstruct_dented_s']:.0f} s ({machine.x_anchor(t['reconstruct_dented_s'])}) (dented). {machine.header()}",
            "",
        ]
    )
    return write_results(path, text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="preview", choices=["preview", "cpu"])
    ap.add_argument("--depth-mm", type=float, default=2.0)
    ap.add_argument("--radius-mm", type=float, default=8.0)
    ap.add_argument("--tolerance", type=float, default=1.5)
    ap.add_argument("--max-unseen", type=float, default=None, help="Default: the inspect command's default.")
    ap.add_argument("--work", type=Path, default=None, help="Keep the captures, twins and reports here (default: a temp dir).")
    ap.add_argument("--part", type=Path, default=SOURCE, help="Textured OBJ (metres) of the nominal part (default: the sample's clamp).")
    ap.add_argument("--out", type=Path, default=None, help="Default: benchmarks/results/dent_<preset>.md")
    args = ap.parse_args()
    import tempfile

    from deploy.inspection_report import DEFAULT_MAX_UNSEEN_PCT

    work = args.work or Path(tempfile.mkdtemp(prefix="cadsplat-dent-"))
    machine = machine_reading()
    res = run(
        work,
        preset=args.preset,
        depth_mm=args.depth_mm,
        radius_mm=args.radius_mm,
        tolerance_mm=args.tolerance,
        max_unseen_pct=DEFAULT_MAX_UNSEEN_PCT if args.max_unseen is None else args.max_unseen,
        source=args.part,
    )
    print(json.dumps(res, indent=1))
    print(write_markdown(res, machine, f"1-min {load_line()}", args.out or RESULTS / f"dent_{args.preset}.md"))
    print(f"captures, twins and reports: {work}")


if __name__ == "__main__":
    main()

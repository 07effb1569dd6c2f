"""Does `cadsplat inspect` tell the truth? Twins of ../shared/data/rig_scenes against their true surfaces.

    python -m benchmarks.bench_inspect TWINS_DIR [--scenes A,B] [--out benchmarks/results/inspect.md]

TWINS_DIR holds one twin per scene, TWINS_DIR/<scene>/twin.json (e.g. made by `cadsplat reconstruct
<scene>/train --library rig_scenes/library --preset cpu`). Per scene:

- the inspection map against the truth: at every CAD vertex the twin's reported deviation and the
  true one (gt_mesh.ply against the CAD model library/<scene>.obj, along the CAD normal, the same
  line cast as `inspect` uses); Pearson r over the vertices `inspect` declares seen, and the share
  of the surface it declares unseen. A true line hit more than 3x farther than the closest point of
  the true surface (plus 0.2 % of the diameter) ran past an edge into another wall: left out, counted.
- geometry: symmetric mean closest-point distance (and p95, pooled over both directions) of the twin's
  deformed mesh and of the CAD model to the true surface, % of the true bounding-sphere diameter.
- the CPU seconds `inspect` took, and beside them (`x anchor`) their ratio to the speed anchor's step read at
  the start of the run (`benchmarks._common.machine_reading`; its ms, the CPU and the load in the header).
"""

from __future__ import annotations

import argparse
import json
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from benchmarks._common import RESULTS, SHARED, MachineReading, load_line, machine_reading, symmetric_surface_distance

DATA = SHARED / "rig_scenes"
SAMPLES = 20_000


def true_deviation(cad_v: np.ndarray, cad_f: np.ndarray, true_v: np.ndarray, true_f: np.ndarray, diameter: float) -> np.ndarray:
    """True signed deviation [V] of the true surface from the CAD along the CAD normal (units of the meshes);
    NaN where the normal line misses, or meets the true surface far beyond its closest point."""
    from reconstruction.inspect import line_deviation, surface_distance, vertex_normals

    normals = vertex_normals(cad_v, cad_f)
    t = line_deviation(cad_v, normals, true_v, true_f, 0.1 * diameter)
    closest = surface_distance(cad_v, true_v, true_f)
    return np.where(np.abs(t) <= 3.0 * closest + 0.002 * diameter, t, np.nan)


def load_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices [V, 3] float64 and faces [F, 3] of a mesh file, duplicate vertices merged (texture seams)."""
    import trimesh

    m = trimesh.load(str(path), force="mesh", process=False)
    m = trimesh.Trimesh(m.vertices, m.faces, process=True)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def scene_row(scene: str, twin_dir: Path) -> dict:
    from reconstruction.inspect import inspect_meshes
    from reconstruction.twin import load_twin

    gt = json.loads((DATA / "scenes" / scene / "gt.json").read_text())
    diameter = 2.0 * gt["object"]["bounding_sphere_radius_m"]
    twin = load_twin(twin_dir)
    row: dict = {"scene": scene, "model_id": twin.model_id, "preset": twin.preset}
    if twin.model_id != scene:
        row["note"] = f"registered {twin.model_id}, not {scene}: no truth to compare the map with"
        return row
    t0 = time.process_time()  # CPU seconds: wall time on a machine shared by several jobs says little
    cad, deformed = twin.load_mesh_cad(), twin.load_mesh_deformed()
    insp = inspect_meshes(
        cad.vertices, cad.faces, cad.face_part, cad.part_names, deformed.vertices, deformed.faces, [c.camera for c in twin.cameras]
    )
    row["inspect_cpu_s"] = time.process_time() - t0
    true_v, true_f = load_mesh(DATA / "scenes" / scene / "gt_mesh.ply")
    truth_mm = 1000.0 * true_deviation(cad.vertices, cad.faces, true_v, true_f, diameter)
    ok = insp.seen & np.isfinite(truth_mm)
    reported = insp.deviation_mm[ok]
    row["pearson_seen"] = float(np.corrcoef(reported, truth_mm[ok])[0, 1]) if ok.sum() > 2 and reported.std() > 0 else float("nan")
    row["rms_true_mm"] = float(np.sqrt(np.mean(truth_mm[ok] ** 2)))
    row["rms_error_mm"] = float(np.sqrt(np.mean((reported - truth_mm[ok]) ** 2)))
    row["truth_left_out_pct"] = float(100.0 * np.mean(~np.isfinite(truth_mm)))
    row["unseen_pct"] = insp.unseen_pct()
    row["out_of_view_pct"] = insp.out_of_view_pct()
    cad_file_v, cad_file_f = load_mesh(DATA / "library" / f"{scene}.obj")
    for name, (v, f) in {"twin": (deformed.vertices, deformed.faces), "cad": (cad_file_v, cad_file_f)}.items():
        mean, p95 = symmetric_surface_distance(v, f, true_v, true_f, SAMPLES)
        row[f"{name}_mean_pct"], row[f"{name}_p95_pct"] = 100.0 * mean / diameter, 100.0 * p95 / diameter
    row["twin_vs_cad_gain_pct"] = 100.0 * (1.0 - row["twin_mean_pct"] / row["cad_mean_pct"])
    row["figure"] = figure_tile(scene, cad.vertices, cad.faces, insp, truth_mm, twin.cameras[0].camera)
    return row


def figure_tile(scene: str, vertices, faces, insp, truth_mm: np.ndarray, camera) -> np.ndarray:
    """[H, 2W, 3] uint8: the CAD mesh from a training view coloured by the reported deviation (left; unseen grey)
    and by the true one (right), on one colour scale: +-the 95th percentile of |true deviation|."""
    import cv2

    from reconstruction.inspect import deviation_colors, render_colored_mesh

    scale = float(np.nanpercentile(np.abs(truth_mm), 95))
    tiles = []
    for dev, seen, label in ((insp.deviation_mm, insp.seen, "reported"), (truth_mm, np.isfinite(truth_mm), "true")):
        rgba = render_colored_mesh(vertices, faces, deviation_colors(dev, seen, scale), camera)
        rgb = (255 * (rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:]))).astype(np.uint8)
        cv2.putText(rgb, f"{scene} {label} (+-{scale:.1f} mm)", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        tiles.append(rgb)
    return np.concatenate(tiles, 1)


def _f(x, fmt: str = "{:.2f}") -> str:
    return "n/a" if x is None or (isinstance(x, float) and not np.isfinite(x)) else fmt.format(x)


def write_markdown(rows: list[dict], twins: Path, machine: MachineReading, load_at_end: str, path: Path) -> str:
    head = (
        "| scene | Pearson r (seen) | RMS true dev (mm) | RMS map error (mm) | unseen % (in no camera's view) | truth left out % | "
        "twin mean % (p95) | CAD mean % (p95) | twin closer than CAD by | inspect CPU s | x anchor |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    )
    lines = [head]
    for r in rows:
        if "note" in r:
            lines.append(f"| {r['scene']} | {r['note']} |||||||||| ")
            continue
        lines.append(
            f"| {r['scene']} | {_f(r['pearson_seen'])} | {_f(r['rms_true_mm'])} | {_f(r['rms_error_mm'])} | {_f(r['unseen_pct'], '{:.1f}')} "
            f"({_f(r.get('out_of_view_pct'), '{:.1f}')}) | "
            f"{_f(r['truth_left_out_pct'], '{:.1f}')} | {_f(r['twin_mean_pct'])} ({_f(r['twin_p95_pct'])}) | "
            f"{_f(r['cad_mean_pct'])} ({_f(r['cad_p95_pct'])}) | {_f(r['twin_vs_cad_gain_pct'], '{:+.1f} %')} | {_f(r['inspect_cpu_s'], '{:.2f}')} "
            f"| {machine.x_anchor(r['inspect_cpu_s'])} |"
        )
    done = [r for r in rows if "note" not in r]
    if done:
        med = lambda k: float(np.nanmedian([r[k] for r in done]))  # noqa: E731
        lines.append(
            f"| **median** ({len(done)}) | **{_f(med('pearson_seen'))}** | {_f(med('rms_true_mm'))} | {_f(med('rms_error_mm'))} | "
            f"{_f(med('unseen_pct'), '{:.1f}')} ({_f(med('out_of_view_pct'), '{:.1f}')}) | {_f(med('truth_left_out_pct'), '{:.1f}')} | "
            f"{_f(med('twin_mean_pct'))} "
            f"({_f(med('twin_p95_pct'))}) | {_f(med('cad_mean_pct'))} ({_f(med('cad_p95_pct'))}) | "
            f"{_f(med('twin_vs_cad_gain_pct'), '{:+.1f} %')} | {_f(med('inspect_cpu_s'), '{:.2f}')} | {machine.x_anchor(med('inspect_cpu_s'))} |"
        )
    text = "\n".join(
        [
            "# Inspection against the truth (rig_scenes)",
            "",
            f"Twins: `{twins}` (preset {', '.join(sorted({r['preset'] for r in rows})) or 'n/a'}); written "
            f"{datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC by `python -m benchmarks.bench_inspect`; {load_at_end} at the end.",
            "",
            "Map: per CAD vertex, `inspect`'s deviation (twin's deformed surface vs CAD along the CAD normal) against the true",
            "one (gt_mesh.ply vs CAD, same line cast); Pearson r and RMS over the vertices `inspect` declares seen (projects",
            "into a training view, unoccluded, normal within 75 deg of the line of sight). Unseen %: share of the CAD surface",
            "area no training view sees (in brackets: the share no training camera has in view at all, the rig's coverage). Truth left out: CAD vertices whose normal line misses the true surface or runs past",
            "an edge (true hit > 3x the closest-point distance + 0.2 % of the diameter). Geometry: symmetric mean closest-point",
            f"distance to gt_mesh.ply, {SAMPLES} area-uniform samples per surface, exact point-to-triangle, % of the true",
            "bounding-sphere diameter (p95 pooled over both directions); the last column is the twin's relative gain over the CAD.",
            f"Figure `{path.with_suffix('.png').name}`: per scene, the reported (left, unseen grey) and true (right) deviation from",
            "the first training view, one colour scale per scene (turbo: blue inside the CAD, red outside).",
            f"Inspect CPU s: the process's CPU seconds for `inspect` (wall time says little on a shared machine); {machine.header()}",
            "",
            *lines,
            "",
        ]
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("twins", type=Path, help="Directory with one twin per scene: TWINS/<scene>/twin.json")
    ap.add_argument("--scenes", default="", help="Comma-separated scene names (default: every scene with a twin).")
    ap.add_argument("--out", type=Path, default=RESULTS / "inspect.md")
    args = ap.parse_args()
    if not DATA.exists():
        raise SystemExit(f"needs the shared data folder ({DATA} is absent)")
    scenes = [s for s in args.scenes.split(",") if s] or sorted(p.name for p in (DATA / "scenes").iterdir())
    machine = machine_reading()
    rows = []
    for scene in scenes:
        twin_dir = args.twins / scene
        if not (twin_dir / "twin.json").exists():
            print(f"{scene}: no twin in {twin_dir}, skipped")
            continue
        row = scene_row(scene, twin_dir)
        print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items() if k != "figure"}))
        rows.append(row)
    if not rows:
        raise SystemExit(f"no twins found under {args.twins}")
    load_at_end = f"1-min {load_line()}"
    tiles = [r.pop("figure") for r in rows if "figure" in r]
    if tiles:
        from calibration.fileio import atomic_write_png

        width = max(t.shape[1] for t in tiles)
        atomic_write_png(
            args.out.with_suffix(".png"),
            np.concatenate([np.pad(t, ((0, 0), (0, width - t.shape[1]), (0, 0)), constant_values=255) for t in tiles], 0),
        )
    print(write_markdown(rows, args.twins, machine, load_at_end, args.out))


if __name__ == "__main__":
    main()

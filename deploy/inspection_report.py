"""The inspection report of a loaded twin, written as one directory: the verdict, per-part CSVs, coloured meshes,
heat maps and a legend (`write_inspection`), and the edge that loads a twin for it (`inspect_twin_dir`).

`cadsplat inspect` and the service's inspect step both write through here; the verdict's exit codes and the report's
layout are described in `deploy/commands/inspect.py`.
"""

from __future__ import annotations

import csv
import io
import re
import shutil
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from reconstruction.inspect import MAX_ANGLE_DEG

if TYPE_CHECKING:
    from calibration.capture import Capture
    from reconstruction.inspect import Inspection, Verdict
    from reconstruction.mesh_io import MeshParts
    from reconstruction.twin import Twin

DEFAULT_TOLERANCE_MM = 1.0
DEFAULT_MAX_UNSEEN_PCT = 25.0
INSPECTION_JSON = "inspection.json"
RENDER_SCALE = 2  # heat maps at twice the training images' size: a dent of a few pixels stays legible


def _safe_name(name: str, taken: set[str]) -> str:
    base = re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("._") or "part"
    out, k = base, 1
    while out in taken:
        k += 1
        out = f"{base}_{k}"
    taken.add(out)
    return out


def _part_csv(insp, rows: np.ndarray, tolerance_mm: float) -> bytes:
    from reconstruction.inspect import tolerance_calls

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(
        [
            "vertex",
            "x_mm",
            "y_mm",
            "z_mm",
            "deviation_mm",
            "uncertainty_mm",
            "status",
            "views",
            "best_angle_deg",
            "pixel_mm",
            "fit_residual_mm",
            "area_mm2",
            "in_view",
        ]
    )
    seen = insp.seen
    out, straddle = tolerance_calls(np.nan_to_num(insp.deviation_mm), insp.uncertainty_mm, tolerance_mm)

    def num(x: float, fmt: str) -> str:
        return fmt.format(x) if np.isfinite(x) else ""

    for i in rows:
        status = "unseen" if not seen[i] else "out" if out[i] else "uncertain" if straddle[i] else "ok"
        x, y, z = insp.vertices_mm[i]
        w.writerow(
            [
                int(i),
                f"{x:.3f}",
                f"{y:.3f}",
                f"{z:.3f}",
                num(insp.deviation_mm[i], "{:.4f}"),
                num(insp.uncertainty_mm[i], "{:.4f}") if seen[i] else "",
                status,
                int(insp.views[i]),
                num(insp.best_angle_deg[i], "{:.1f}"),
                num(insp.footprint_mm[i], "{:.4f}"),
                num(insp.residual_mm[i], "{:.4f}"),
                f"{insp.area_mm2[i]:.4f}",
                int(insp.in_view[i]),
            ]
        )
    return buf.getvalue().encode()


def _ply_bytes(vertices: np.ndarray, faces: np.ndarray, rgb: np.ndarray, insp) -> bytes:
    from plyfile import PlyData, PlyElement

    vert = np.empty(
        len(vertices),
        dtype=[
            ("x", "f4"),
            ("y", "f4"),
            ("z", "f4"),
            ("red", "u1"),
            ("green", "u1"),
            ("blue", "u1"),
            ("deviation_mm", "f4"),
            ("uncertainty_mm", "f4"),
            ("views", "u1"),
        ],
    )
    vert["x"], vert["y"], vert["z"] = np.asarray(vertices, np.float32).T
    vert["red"], vert["green"], vert["blue"] = rgb.T
    vert["deviation_mm"] = np.where(insp.seen, insp.deviation_mm, np.nan)
    vert["uncertainty_mm"] = np.where(insp.seen, insp.uncertainty_mm, np.nan)
    vert["views"] = np.minimum(insp.views, 255)
    face = np.empty(len(faces), dtype=[("vertex_indices", "i4", (3,))])
    face["vertex_indices"] = faces
    buf = io.BytesIO()
    PlyData([PlyElement.describe(vert, "vertex"), PlyElement.describe(face, "face")], byte_order="<").write(buf)
    return buf.getvalue()


def _glb_bytes(parts, rgb: np.ndarray) -> bytes:
    import trimesh

    scene = trimesh.Scene()
    rgba = np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], 1)
    for p, name in enumerate(parts.part_names):
        sel = np.flatnonzero(parts.face_part == p)
        if sel.size == 0:
            continue
        used, faces = np.unique(parts.faces[sel], return_inverse=True)
        mesh = trimesh.Trimesh(parts.vertices[used], faces.reshape(-1, 3), vertex_colors=rgba[used], process=False)
        scene.add_geometry(mesh, node_name=name, geom_name=name)
    return scene.export(file_type="glb")


def _legend_png(range_mm: float, tolerance_mm: float) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import Normalize

    fig, ax = plt.subplots(figsize=(5.0, 1.1), dpi=100, layout="constrained")
    bar = fig.colorbar(plt.cm.ScalarMappable(Normalize(-range_mm, range_mm), "turbo"), cax=ax, orientation="horizontal")
    for t in (-tolerance_mm, tolerance_mm):
        ax.axvline(t, color="black", linewidth=1.5)
    bar.set_label("deviation from CAD along its normal, mm (- inside, + outside); dark grey: unseen; lines: tolerance")
    bar.ax.xaxis.label.set_size(7)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


def inspect_twin_dir(
    twin_dir: Path,
    out_dir: Path,
    *,
    tolerance_mm: float,
    max_unseen_pct: float,
    turntable: int = 24,
    max_angle_deg: float = MAX_ANGLE_DEG,
    renders: bool = True,
    capture_dir: Path | None = None,
) -> dict:
    """Load the twin at `twin_dir` (and the masks of the capture at `capture_dir`, when given) and `write_inspection`
    of it under `out_dir`; returns the inspection document."""
    from calibration.capture import read_capture
    from reconstruction.twin import load_twin

    _check_settings(tolerance_mm, max_unseen_pct, Path(out_dir))
    twin = load_twin(twin_dir)
    masks = None if capture_dir is None else capture_masks_for(twin, read_capture(capture_dir))
    return write_inspection(
        twin,
        out_dir,
        tolerance_mm=tolerance_mm,
        max_unseen_pct=max_unseen_pct,
        turntable=turntable,
        max_angle_deg=max_angle_deg,
        renders=renders,
        twin_label=str(twin_dir),
        masks=masks,
    )


def _check_settings(tolerance_mm: float, max_unseen_pct: float, out: Path) -> None:
    if not tolerance_mm > 0:
        raise ValueError(f"the tolerance must be a positive number of millimetres, got {tolerance_mm}")
    if not 0 <= max_unseen_pct <= 100:
        raise ValueError(f"the unseen share allowed must be a percentage in [0, 100], got {max_unseen_pct}")
    if out.exists() and not (out / INSPECTION_JSON).exists():
        raise ValueError(f"{out} exists and is not an earlier inspection; choose another --out")


def capture_masks_for(twin: Twin, capture: Capture) -> list[np.ndarray]:
    """The capture's masks [H, W] bool at its own resolution, one per twin camera (matched by image path). Raises
    ValueError naming the first twin view the capture does not hold, or a capture without masks."""
    by_path = {f.file_path: i for i, f in enumerate(capture.frames)}
    out = []
    for cam in twin.cameras:
        if cam.file_path not in by_path:
            raise ValueError(f"{capture.root} holds no view {cam.file_path}: give the capture the twin was made from")
        mask = capture.mask(by_path[cam.file_path])
        if mask is None:
            raise ValueError(f"{capture.root} has no mask for {cam.file_path}: refining the map needs the capture's masks")
        out.append(np.asarray(mask, bool))
    return out


def write_inspection(
    twin: Twin,
    out_dir: Path,
    *,
    tolerance_mm: float,
    max_unseen_pct: float,
    turntable: int = 24,
    max_angle_deg: float = MAX_ANGLE_DEG,
    renders: bool = True,
    twin_label: str | None = None,
    masks: list[np.ndarray] | None = None,
) -> dict:
    """Inspect the loaded `twin` and write everything under `out_dir` (built beside it, renamed into place); with
    `masks` (one [H, W] bool per twin camera, the capture's own resolution) the map is refined at the outlines.

    Returns the inspection document (what inspection.json holds; `twin_label` names the twin there, default its
    root). Raises TwinError/ValueError with one sentence when the twin cannot be inspected or `out_dir` is something
    else than an earlier inspection.
    """
    from calibration.fileio import sha256_bytes
    from reconstruction.inspect import deviation_colors, inspect_twin, part_reports, verdict

    out = Path(out_dir)
    _check_settings(tolerance_mm, max_unseen_pct, out)
    cad = twin.load_mesh_cad()
    insp = inspect_twin(twin, masks, cad=cad, max_angle_deg=max_angle_deg)
    result = verdict(insp, tolerance_mm, max_unseen_pct)
    range_mm = 2.0 * tolerance_mm
    rgb = (deviation_colors(insp.deviation_mm, insp.seen, range_mm) * 255 + 0.5).astype(np.uint8)
    files = _report_files(twin, cad, insp, rgb, tolerance_mm, renders=renders, turntable=turntable)
    doc = {
        "format": "cadsplat-inspection/1",
        "twin": twin_label if twin_label is not None else str(twin.root),
        "model_id": twin.model_id,
        "verdict": result.to_dict(),
        "settings": _settings_doc(tolerance_mm, max_unseen_pct, max_angle_deg, refined_by_masks=masks is not None),
        "surface": _surface_doc(insp, result, num_cameras=len(twin.cameras)),
        "parts": [r.to_dict() for r in part_reports(insp, tolerance_mm)],
        "sha256": {name: sha256_bytes(data) for name, data in files.items()},
    }
    _publish(out, files, doc, result.line)
    return doc


def _report_files(
    twin: Twin, cad: MeshParts, insp: Inspection, rgb: np.ndarray, tolerance_mm: float, *, renders: bool, turntable: int
) -> dict[str, bytes]:
    """The report's files by relative name: per-part CSVs, the coloured meshes and, with `renders`, the heat maps
    (training views, then `turntable` orbit views when non-zero) and the legend. rgb: [V, 3] uint8."""
    from calibration.fileio import encode_png
    from deploy.commands.render import orbit_cameras
    from reconstruction.inspect import render_colored_mesh

    files: dict[str, bytes] = {}
    taken: set[str] = set()
    for p, name in enumerate(insp.part_names):
        files[f"parts/{_safe_name(name, taken)}.csv"] = _part_csv(insp, np.flatnonzero(insp.part == p), tolerance_mm)
    files["deviation.ply"] = _ply_bytes(cad.vertices, cad.faces, rgb, insp)
    files["deviation.glb"] = _glb_bytes(cad, rgb)
    if renders:
        colors = rgb / 255.0
        views = [(f"views/{Path(c.file_path).stem}.png", c.camera) for c in twin.cameras]
        views += [(f"turntable/{name}", cam) for name, cam in orbit_cameras(twin, turntable)] if turntable else []
        for name, cam in views:
            big = cam.scaled(RENDER_SCALE * cam.width, RENDER_SCALE * cam.height)
            files[name] = encode_png(render_colored_mesh(cad.vertices, cad.faces, colors, big))
        files["legend.png"] = _legend_png(2.0 * tolerance_mm, tolerance_mm)
    return files


def _settings_doc(tolerance_mm: float, max_unseen_pct: float, max_angle_deg: float, *, refined_by_masks: bool) -> dict:
    """inspection.json's settings block: the thresholds and what each reported quantity means."""
    range_mm = 2.0 * tolerance_mm
    return {
        "tolerance_mm": tolerance_mm,
        "max_unseen_pct": max_unseen_pct,
        "max_angle_deg": max_angle_deg,
        "refined_by_masks": refined_by_masks,
        "deviation": "signed distance from the CAD surface to the twin's deformed surface along the outward "
        "CAD vertex normal, mm; + outside the CAD (bulge), - inside (dent); read after the best-fit alignment of the seen "
        "surface (surface.alignment: the small motion taken out, rigid on a metric rig, a similarity where the rig's "
        "scale is not known), since where a loose part lies against its CAD frame is placement, not shape",
        "seen": f"projects inside a training image, unoccluded, normal within {max_angle_deg:g} deg of the line of sight",
        "in_view": "as seen, occluded or not: unseen surface in no camera's view is the rig's coverage",
        "uncertainty": "expanded (k = 2) uncertainty of the deviation, mm: the views that see the vertex (a move along "
        "the normal shows by sin(angle) / pixel size per view; the best view decides) and the map's "
        "local fit residual; PASS needs every seen vertex inside the tolerance by more than it",
        "colour_range_mm": [-range_mm, range_mm],
    }


def _surface_doc(insp: Inspection, result: Verdict, *, num_cameras: int) -> dict:
    """inspection.json's surface block: area, unseen / out-of-view / uncertain / out shares and views per vertex."""
    return {
        "vertices": int(len(insp.views)),
        "area_mm2": float(insp.area_mm2.sum()),
        "unseen_pct": result.unseen_pct,
        "out_of_view_pct": result.out_of_view_pct,
        "uncertain_pct": result.straddling_pct,
        "out_pct": result.out_pct,
        "uncertainty_median_mm": float(np.median(insp.uncertainty_mm[insp.seen])) if insp.seen.any() else None,
        "alignment": insp.alignment.to_dict() if insp.alignment is not None else None,
        "views_per_vertex": {str(k): int(n) for k, n in enumerate(np.bincount(insp.views, minlength=num_cameras + 1))},
    }


def _publish(out: Path, files: dict[str, bytes], doc: dict, verdict_line: str) -> None:
    """Write files, inspection.json and verdict.txt into a fresh directory beside `out`, then rename it into place."""
    from calibration.fileio import atomic_write_bytes, atomic_write_json, fsync_dir, publish_dir

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".incoming", dir=out.parent))
    try:
        for name, data in files.items():
            (tmp / name).parent.mkdir(parents=True, exist_ok=True)
            atomic_write_bytes(tmp / name, data)
        for sub in {(tmp / name).parent for name in files}:
            fsync_dir(sub)
        atomic_write_json(tmp / INSPECTION_JSON, doc)
        atomic_write_bytes(tmp / "verdict.txt", (verdict_line + "\n").encode())
        fsync_dir(tmp)
        publish_dir(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise

"""What limits `cadsplat inspect`'s map? Its error |reported - true| on ../shared/data/rig_scenes, split into parts.

    python -m benchmarks.bench_inspect_error_budget TWINS_DIR [--data-dir DIR] [--scenes A,B] [--reading FILE]
        [--out benchmarks/results/inspect_error_budget.md] [--json FILE]

TWINS_DIR holds one twin per scene (as for `bench_inspect_truth`); nothing is trained. Per scene, over the CAD
vertices the map (`mesh`, today's default) calls seen and the truth reaches, median and p90 in mm and in pixels at
the object (each vertex over its own pixel footprint), of:

- **map**: |reported - true|, the truth as `bench_inspect_truth` defines it (gt_mesh against the CAD along the CAD
  normal);
- **definition**: |true along the normal - true as the signed closest point|: how much the yardstick itself moves
  between two reasonable definitions;
- **map against closest-point truth**: |reported - that other truth|;
- **twin surface**: each deformed-mesh vertex's distance to the true surface (the twin's geometry, whatever reads it);
- **map read by the normal line**: the deviation read as the deformed surface's crossing of the CAD normal line
  (`inspect.line_deviation`, as a reference surface is read) instead of the vertex's own move along its normal;
  **map and truth by closest point**: both read as the signed closest point from the CAD vertex;
- **bias removed** / **pose-like removed**: the map's signed error less its median (one offset along every normal,
  such as the alpha-1/2 and mask steps the pipeline adds), and less its least-squares fit by an offset plus the
  normal components of the 7 infinitesimal similarities (what a pose or scale error makes);
- **map less its own best-fit rigid motion**: the reported map less its least-squares fit by the normal components
  of the 6 rigid motions (no truth used: a metrology best-fit alignment), against the truth;
- **cameras**: the twin's refined cameras against the true ones, RMS reprojection px of the true surface, as they
  are and after the one Sim(3) that best explains all of them (per-camera residual); the capture's recorded
  (noisy) cameras likewise; and the map's error with the deformed mesh carried by that Sim(3) into the true frame;
- **oracle fields**: the best the twin's deformation parametrisation can do: anchor offsets ([M, 3], the twin's
  farthest-point anchors over its canonical splats, blended to the vertices with the field's inverse-distance
  weights, its rigid motion projected out as training does) fitted by least squares to the true deviation along
  the normals, at the twin's anchor count and fewer;
- **twin's field alone**: the twin's smooth field recovered from its splats (the anchor offsets whose blend best
  fits the splats' moves; the per-splat normal moves stay in the residual), read at the vertices plus the map's
  median remainder (the uniform steps): is the map's rough part the per-splat moves?
- **chord**: the CAD's faces with their vertices on the true surface: how far face centres lie from it (the error
  a flat-faced mesh of this density makes even with perfect vertices);
- **smooth / rough part**: the signed error's mean over each vertex's 16 nearest same-side neighbours, and the
  rest: a smooth error is a misplaced surface the views did not pin, a rough one noise from vertex to vertex;
- **where**: the map's error by number of views, best angle (the view most along the normal), the most oblique
  view that sees the vertex, the number of views in which the vertex lies on the
  object's outline (normal more than 75 deg from the line of sight), wall thickness (in pixels) and reported
  uncertainty, with each bin's share of the vertices and of the p90 tail.

Writes benchmarks/results/inspect_error_budget.md.
"""

from __future__ import annotations

import argparse
import json
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import LinearOperator, lsqr

from benchmarks._common import RESULTS, SHARED, load_line

DATA = SHARED / "rig_scenes"
ORACLE_ANCHORS = (64, 256)  # fewer anchors than the twin's, to see how many the truth's deformation needs
FIT_POINTS = 2_000
SMOOTH_NEIGHBOURS = 16  # the neighbourhood the error's smooth part is its mean over (as the map's local fit residual's)
# A twin frame turned further than this from the true one is a near-symmetric part registered to another of its
# symmetric poses (the map is still right in it): carrying its mesh by that turn would measure the symmetry.
SYMMETRIC_TURN_DEG = 10.0


# ---------------------------------------------------------------------------------------- pure parts


def closest_signed_deviation(points: np.ndarray, normals: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Signed distance [P] from `points` [P, 3] to the closest point of the mesh (`vertices` [V, 3], `faces`
    [F, 3]), positive where that point lies on the side the unit `normals` [P, 3] point to."""
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
    closest, dist, _ = trimesh.proximity.closest_point(mesh, np.asarray(points, np.float64))
    side = np.einsum("pd,pd->p", closest - points, normals)
    return np.where(side < 0, -dist, dist)


def fit_residual(values: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """values [P] less their least-squares fit by the columns of `basis` [P, K]."""
    coef, *_ = np.linalg.lstsq(basis, values, rcond=None)
    return values - basis @ coef


def blend_matrix(points: np.ndarray, anchors: np.ndarray, k: int) -> sp.csr_matrix:
    """[P, M] sparse: row p holds point p's inverse-distance weights on its k nearest of `anchors` [M, 3], as the
    deformation field blends its anchors' offsets (`deformation.idw_weights`)."""
    from reconstruction.deformation import idw_weights

    idx, w = idw_weights(points, anchors, k)
    rows = np.repeat(np.arange(len(points)), idx.shape[1])
    return sp.csr_matrix((w.ravel().astype(np.float64), (rows, idx.ravel())), shape=(len(points), len(anchors)))


def rigid_projector(anchors: np.ndarray, center: np.ndarray, radius: float):
    """x [3M] -> x less its least-squares rigid motion (3 translations, 3 rotations) over `anchors` [M, 3]: what
    training projects out of the field's anchor offsets (`FieldConfig.project_similarity`, keeping the scale)."""
    import torch

    from reconstruction.deformation import similarity_basis

    x = torch.from_numpy((np.asarray(anchors, np.float64) - center) / radius)
    basis = similarity_basis(x, with_scale=False).numpy()  # [3M, 6]
    pinv = np.linalg.pinv(basis)
    return lambda v: v - basis @ (pinv @ v)


def oracle_normal_moves(blend: sp.csr_matrix, normals: np.ndarray, target: np.ndarray, project=None, damp: float = 1e-6) -> np.ndarray:
    """The normal moves [P] (n_p . sum_m blend[p, m] a_m) of the anchor offsets a [M, 3] (rigid part projected out by
    `project` when given) that best fit `target` [P] in least squares; `blend` [P, M], unit `normals` [P, 3]."""
    m = blend.shape[1]
    cols = [sp.diags(normals[:, d]) @ blend for d in range(3)]
    a_mat = sp.hstack(cols).tocsr()  # [P, 3M], unknowns ordered (x of all anchors, y ..., z ...)

    def to_rows(v):  # [3M] (x..., y..., z...) <-> [M, 3] flattened row-major, the projector's order
        return v.reshape(3, m).T.ravel()

    def from_rows(v):
        return v.reshape(m, 3).T.ravel()

    proj = (lambda v: from_rows(project(to_rows(v)))) if project is not None else (lambda v: v)
    op = LinearOperator(a_mat.shape, matvec=lambda v: a_mat @ proj(v), rmatvec=lambda y: proj(a_mat.T @ y))
    sol = lsqr(op, target, damp=damp, atol=1e-10, btol=1e-10, iter_lim=5000)[0]
    return a_mat @ proj(sol)


def error_stats(err_mm: np.ndarray, footprint_mm: np.ndarray) -> dict:
    """Median and p90 of |err| [P] in mm and in pixels at the object (each over its footprint [P], mm per px)."""
    e = np.abs(np.asarray(err_mm, np.float64))
    ok = np.isfinite(e) & np.isfinite(footprint_mm)
    e, px = e[ok], e[ok] / footprint_mm[ok]
    if not ok.any():
        return {"n": 0, "median_mm": np.nan, "p90_mm": np.nan, "median_px": np.nan, "p90_px": np.nan}
    return {
        "n": int(ok.sum()),
        "median_mm": float(np.median(e)),
        "p90_mm": float(np.percentile(e, 90)),
        "median_px": float(np.median(px)),
        "p90_px": float(np.percentile(px, 90)),
    }


def binned(err_px: np.ndarray, key: np.ndarray, edges: list[float], labels: list[str]) -> list[dict]:
    """Per bin of `key` [P] (bins [edges[i], edges[i + 1]); NaN keys in a last bin when `labels` has one more):
    its share of the vertices, median error (px) and share of the p90 tail (err_px [P] above its 90th percentile)."""
    tail = err_px > np.percentile(err_px, 90)
    out = []
    for i, label in enumerate(labels):
        m = (key >= edges[i]) & (key < edges[i + 1]) if i + 1 < len(edges) else ~np.isfinite(key)
        out.append(
            {
                "bin": label,
                "share_pct": float(100.0 * m.mean()),
                "median_px": float(np.median(err_px[m])) if m.any() else float("nan"),
                "tail_pct": float(100.0 * (m & tail).sum() / max(tail.sum(), 1)),
            }
        )
    return out


def wall_thickness(points: np.ndarray, normals: np.ndarray, vertices: np.ndarray, faces: np.ndarray, reach: float) -> np.ndarray:
    """Distance [P] from each point inward along -normal to the part's other wall (a face facing away from the
    point's), within `reach`; NaN where none is found that way."""
    from reconstruction.inspect import line_deviation

    t = line_deviation(points, -np.asarray(normals, np.float64), vertices, faces, reach)
    return np.where(t > 0, t, np.nan)


def neighbour_mean(points: np.ndarray, normals: np.ndarray, values: np.ndarray, k: int = SMOOTH_NEIGHBOURS) -> np.ndarray:
    """Mean [P] of `values` [P] over each point's k nearest other points (points [P, 3]) on its own side of the
    surface (unit normals [P, 3] within 60 deg of its own, so a thin part's other wall is left out); the point's own
    value where none is."""
    from scipy.spatial import cKDTree

    p = np.asarray(points, np.float64)
    k = min(k + 1, len(p))
    _, nb = cKDTree(p).query(p, k=k)
    nb = nb[:, 1:]
    same = np.einsum("pd,pkd->pk", normals, normals[nb]) >= 0.5
    total = np.where(same, values[nb], 0.0).sum(1)
    count = same.sum(1)
    return np.where(count > 0, total / np.maximum(count, 1), values)


def silhouette_views(points: np.ndarray, normals: np.ndarray, cameras, grazing_deg: float = 75.0) -> np.ndarray:
    """[P] how many of `cameras` have each point (points [P, 3], unit normals [P, 3]) inside their image with its
    normal more than `grazing_deg` from the line of sight: where it lies on (or next to) the object's outline in that
    view, occlusion aside."""
    from calibration.camera import project_points

    out = np.zeros(len(points), np.int64)
    sin_min = np.cos(np.radians(grazing_deg))
    for cam in cameras:
        uv, z = project_points(points, cam.K, cam.viewmat, near=1e-6)
        inside = (z > 1e-6) & np.all(np.isfinite(uv), 1)
        inside &= (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        to_cam = cam.center - points
        cos = np.einsum("pd,pd->p", normals, to_cam) / np.linalg.norm(to_cam, axis=1)
        out += inside & (np.abs(cos) < sin_min)
    return out


def most_oblique_deg(seen: np.ndarray, cos: np.ndarray) -> np.ndarray:
    """[V] the largest angle (deg) between a vertex's normal and the line of sight of a camera that sees it (seen
    [C, V] bool, cos [C, V]); NaN where none does. Small: every view looks along the normal, where a move along it
    moves the point along every line of sight and no outline shows it."""
    cos_min = np.where(seen, cos, np.inf).min(0)
    return np.where(np.isfinite(cos_min), np.degrees(np.arccos(np.clip(cos_min, -1.0, 1.0))), np.nan)


def chord_gap(vertices_on_truth: np.ndarray, faces: np.ndarray, true_v: np.ndarray, true_f: np.ndarray) -> np.ndarray:
    """Distance [F] of each face's centre to the true surface when the faces' vertices [V, 3] lie on it."""
    from reconstruction.inspect import surface_distance

    return surface_distance(np.asarray(vertices_on_truth)[np.asarray(faces)].mean(1), true_v, true_f)


# ---------------------------------------------------------------------------------------- one scene


def scene_budget(scene: str, twin_dir: Path, data: Path = DATA) -> dict:
    """Every part of the budget for one scene's twin (see the module's docstring)."""
    from benchmarks.bench_inspect import load_mesh, true_deviation
    from benchmarks.bench_noise_ceiling import best_sim3, project
    from benchmarks.bench_rig_scenes import surface_points
    from calibration.sim3 import Sim3
    from reconstruction.deformation import farthest_point_indices, normal_similarity_basis
    from reconstruction.inspect import (
        inspect_twin,
        line_deviation,
        normal_deviation,
        point_visibility,
        surface_distance,
        vertex_normals,
    )
    from reconstruction.twin import load_twin

    gt = json.loads((data / "scenes" / scene / "gt.json").read_text())
    twin = load_twin(twin_dir)
    if twin.model_id != scene:
        return {"scene": scene, "note": f"registered {twin.model_id}, not {scene}"}
    cad, deformed = twin.load_mesh_cad(), twin.load_mesh_deformed()
    cad_v, cad_f = np.asarray(cad.vertices, np.float64), np.asarray(cad.faces, np.int64)
    normals = vertex_normals(cad_v, cad_f)
    true_v, true_f = load_mesh(data / "scenes" / scene / "gt_mesh.ply")
    diameter = 2.0 * gt["object"]["bounding_sphere_radius_m"]
    truth = true_deviation(cad_v, cad_f, true_v, true_f, diameter)
    insp = inspect_twin(twin, cad=cad, deformed=deformed)
    ok = insp.seen & np.isfinite(truth)
    fp = insp.footprint_mm[ok]
    err = (insp.deviation_mm - 1000.0 * truth)[ok]  # signed, mm
    row: dict = {"scene": scene, "vertices": int(ok.sum()), "pixel_mm": float(np.median(fp)), "parts": {}}
    parts = row["parts"]
    parts["map"] = error_stats(err, fp)
    row["bias_mm"] = float(np.median(err))

    closest = closest_signed_deviation(cad_v, normals, true_v, true_f)
    parts["definition"] = error_stats(1000.0 * (truth - closest)[ok], fp)
    parts["map against closest-point truth"] = error_stats(insp.deviation_mm[ok] - 1000.0 * closest[ok], fp)
    twin_v = np.asarray(deformed.vertices, np.float64)
    parts["twin surface"] = error_stats(1000.0 * surface_distance(twin_v[ok], true_v, true_f), fp)
    line_read = line_deviation(cad_v, normals, twin_v, np.asarray(deformed.faces, np.int64), 0.1 * diameter)
    parts["map read by the normal line"] = error_stats(1000.0 * (line_read - truth)[ok], fp)
    twin_closest = closest_signed_deviation(cad_v, normals, twin_v, np.asarray(deformed.faces, np.int64))
    parts["map and truth by closest point"] = error_stats(1000.0 * (twin_closest - closest)[ok], fp)
    parts["bias removed"] = error_stats(err - np.median(err), fp)
    smooth = neighbour_mean(cad_v[ok], normals[ok], err)
    parts["smooth part (16-neighbour mean)"] = error_stats(smooth, fp)
    parts["rough part (less that mean)"] = error_stats(err - smooth, fp)
    center = 0.5 * (cad_v.min(0) + cad_v.max(0))
    sim_basis = normal_similarity_basis(cad_v[ok], normals[ok], center, 0.5 * diameter)
    rigid_basis = normal_similarity_basis(cad_v[ok], normals[ok], center, 0.5 * diameter, with_scale=False)
    aligned = fit_residual(insp.deviation_mm[ok], rigid_basis)
    parts["map less its own best-fit rigid motion"] = error_stats(aligned - 1000.0 * truth[ok], fp)
    parts["pose-like removed"] = error_stats(fit_residual(err, np.column_stack([np.ones(len(err)), sim_basis])), fp)

    # Cameras: the twin's against the true ones, through 2,000 points of the true surface.
    pts = surface_points(true_v, true_f, FIT_POINTS)
    true_c2w = np.stack(gt["train"]["c2w_opencv_object"])
    noisy_c2w = np.stack(gt["train"]["c2w_opencv_object_noisy"])
    by_path = {Path(p).name: i for i, p in enumerate(gt["train"]["file_path"])}
    order = [by_path[Path(c.file_path).name] for c in twin.cameras]
    twin_c2w = np.stack([c.c2w_object_opencv for c in twin.cameras])
    Ks = np.stack([c.K for c in twin.cameras])
    sim_twin, rms_twin_best, rms_twin = best_sim3(twin_c2w, true_c2w[order], Ks, pts, Sim3.identity())
    _, rms_noisy_best, rms_noisy = best_sim3(noisy_c2w[order], true_c2w[order], Ks, pts, Sim3.identity())
    per_cam = [
        float(np.sqrt(np.mean(np.sum((project(pts, c, k) - project(pts, t, k)) ** 2, 1))))
        for c, t, k in zip(sim_twin.apply_to_c2w(twin_c2w), true_c2w[order], Ks)
    ]
    row["cameras"] = {
        "twin_rms_px": rms_twin,
        "twin_rms_px_after_sim3": rms_twin_best,
        "twin_worst_camera_px_after_sim3": max(per_cam),
        "noisy_rms_px": rms_noisy,
        "noisy_rms_px_after_sim3": rms_noisy_best,
        "sim3_scale": sim_twin.scale,
        "sim3_translation_mm": float(1000.0 * np.linalg.norm(sim_twin.translation)),
        "sim3_rotation_deg": float(np.degrees(np.arccos(np.clip((np.trace(sim_twin.rotation) - 1) / 2, -1, 1)))),
    }
    if row["cameras"]["sim3_rotation_deg"] <= SYMMETRIC_TURN_DEG:
        carried = normal_deviation(cad_v, normals, sim_twin.apply(twin_v))
        parts["mesh in true frame"] = error_stats((1000.0 * (carried - truth))[ok], fp)
    else:
        row["note"] = "the twin's frame is a symmetric copy of the true one: the mesh is not carried"
        parts["mesh in true frame"] = None

    # Oracle fields: anchors as the twin's field chose them.
    # Twins written before the whole configuration was recorded carry their field's in the choices.
    field_cfg = twin.config.get("field") or twin.choices.get("deformation", {}).get("value", {})
    seed = int(twin.training.get("seed", 0))
    canon = np.asarray(twin.means_canonical, np.float64)
    c_field = 0.5 * (canon.min(0) + canon.max(0))
    r_field = float(np.linalg.norm(canon - c_field, axis=1).max())
    k = int(field_cfg.get("anchor_k", 4))
    twin_anchors = field_cfg.get("num_anchors") or len(canon)
    row["anchors"] = int(twin_anchors)
    for m in sorted({*ORACLE_ANCHORS, int(twin_anchors)}):
        anchors = canon[farthest_point_indices(canon, m, seed)]
        blend = blend_matrix(cad_v[ok], anchors, k)
        project_rigid = rigid_projector(anchors, c_field, r_field) if field_cfg.get("project_similarity") else None
        fit = oracle_normal_moves(blend, normals[ok], truth[ok], project_rigid)
        parts[f"oracle field, {m} anchors"] = error_stats(1000.0 * (fit - truth[ok]), fp)

    # The twin's own field, recovered from its splats: the anchor offsets that best blend to the splats' moves (the
    # per-splat normal moves are left in the residual), blended to the vertices, plus the map's median remainder
    # (the pipeline's uniform alpha-1/2 and mask steps).
    anchors = canon[farthest_point_indices(canon, int(twin_anchors), seed)]
    splat_moves = np.asarray(twin.gaussians.means, np.float64) - canon
    at_splats = blend_matrix(canon, anchors, k)
    anchor_moves = np.column_stack([lsqr(at_splats, splat_moves[:, d], atol=1e-10, btol=1e-10)[0] for d in range(3)])
    field_dev = np.einsum("pd,pd->p", blend_matrix(cad_v, anchors, k) @ anchor_moves, normals)
    field_map = 1000.0 * field_dev[ok] + np.median(insp.deviation_mm[ok] - 1000.0 * field_dev[ok])
    parts["twin's field alone (+ uniform step)"] = error_stats(field_map - 1000.0 * truth[ok], fp)
    on_truth = cad_v + np.nan_to_num(truth)[:, None] * normals
    faces_ok = ok[cad_f].all(1)
    chord = chord_gap(on_truth, cad_f[faces_ok], true_v, true_f)
    face_fp = np.nanmedian(insp.footprint_mm[cad_f[faces_ok]], 1)
    parts["chord (face centres)"] = error_stats(1000.0 * chord, face_fp)

    # Where the error lies; visibility judged as the map judges it, on the deformed surface.
    vis = point_visibility(twin_v, vertex_normals(twin_v, cad_f), twin_v, cad_f, [c.camera for c in twin.cameras])
    err_px = np.abs(err) / fp
    thick_px = 1000.0 * wall_thickness(cad_v, normals, cad_v, cad_f, diameter)[ok] / fp
    u_rank = np.argsort(np.argsort(insp.uncertainty_mm[ok])) / max(ok.sum() - 1, 1)
    row["where"] = {
        "views": binned(err_px, insp.views[ok].astype(float), [1, 2, 3, 4, np.inf], ["1", "2", "3", ">= 4"]),
        "best angle deg": binned(err_px, insp.best_angle_deg[ok], [0, 30, 50, 65, 90], ["< 30", "30-50", "50-65", ">= 65"]),
        "wall thickness px": binned(err_px, thick_px, [0, 3, 10, np.inf], ["< 3", "3-10", ">= 10", "no wall found"]),
        "most oblique seeing view deg": binned(
            err_px, most_oblique_deg(vis.seen, vis.cos)[ok], [0, 45, 60, 90], ["< 45", "45-60", ">= 60"]
        ),
        "outline in views": binned(
            err_px,
            silhouette_views(cad_v[ok], normals[ok], [c.camera for c in twin.cameras]).astype(float),
            [0, 1, 2, 3, np.inf],
            ["0", "1", "2", ">= 3"],
        ),
        "uncertainty tercile": binned(err_px, u_rank, [0, 1 / 3, 2 / 3, 1.0 + 1e-9], ["low", "middle", "high"]),
    }
    row["uncertainty_vs_error_r"] = float(np.corrcoef(insp.uncertainty_mm[ok], np.abs(err))[0, 1])
    return row


# ---------------------------------------------------------------------------------------- report


def _f(x, fmt: str = "{:.2f}") -> str:
    return "n/a" if x is None or (isinstance(x, float) and not np.isfinite(x)) else fmt.format(x)


def budget_table(rows: list[dict]) -> list[str]:
    """One line per scene and part: median / p90 in px and mm."""
    done = [r for r in rows if "parts" in r]
    names = list(done[0]["parts"]) if done else []
    lines = [
        "| part | " + " | ".join(r["scene"] for r in done) + " | median over scenes, px |",
        "|---|" + "---:|" * (len(done) + 1),
    ]
    for name in names:
        have = [r["parts"][name] for r in done if r["parts"].get(name) is not None]
        over = f"{_f(float(np.median([p['median_px'] for p in have])))} / {_f(float(np.median([p['p90_px'] for p in have])))} ({len(have)})"
        cells = []
        for r in done:
            p = r["parts"].get(name)
            cells.append(
                "n/a (symmetric copy)"
                if p is None
                else f"{_f(p['median_px'])} / {_f(p['p90_px'])} px ({_f(p['median_mm'])} / {_f(p['p90_mm'])} mm)"
            )
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {over} |")
    return lines


def camera_table(rows: list[dict]) -> list[str]:
    lines = [
        "| scene | pixel mm | bias mm | twin cams RMS px | after one Sim(3) | worst camera | recorded (noisy) cams RMS px "
        "| after one Sim(3) | Sim(3): scale, mm, deg | r(U, error) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---|---:|",
    ]
    for r in rows:
        if "cameras" not in r:
            lines.append(f"| {r['scene']} | {r.get('note', '')} |" + " |" * 8)
            continue
        c = r["cameras"]
        lines.append(
            f"| {r['scene']} | {_f(r['pixel_mm'])} | {r['bias_mm']:+.2f} | {_f(c['twin_rms_px'])} | {_f(c['twin_rms_px_after_sim3'])} "
            f"| {_f(c['twin_worst_camera_px_after_sim3'])} | {_f(c['noisy_rms_px'])} | {_f(c['noisy_rms_px_after_sim3'])} "
            f"| {c['sim3_scale']:.4f}, {c['sim3_translation_mm']:.2f}, {c['sim3_rotation_deg']:.3f} | {_f(r['uncertainty_vs_error_r'])} |"
        )
    return lines


def where_table(rows: list[dict], key: str) -> list[str]:
    """Per scene: each bin's share of vertices / median error px / share of the p90 tail."""
    done = [r for r in rows if "where" in r]
    if not done:
        return []
    bins = [b["bin"] for b in done[0]["where"][key]]
    lines = [f"| {key} | " + " | ".join(r["scene"] for r in done) + " |", "|---|" + "---:|" * len(done)]
    for i, b in enumerate(bins):
        cells = [
            f"{_f(w['share_pct'], '{:.0f}')} % / {_f(w['median_px'])} px / {_f(w['tail_pct'], '{:.0f}')} %"
            for w in (r["where"][key][i] for r in done)
        ]
        lines.append(f"| {b} | " + " | ".join(cells) + " |")
    return lines


def write_markdown(rows: list[dict], twins: Path, load_at_end: str, reading: str, path: Path) -> str:
    text = [
        "# What limits the inspection map's error (rig_scenes, `cpu` twins)",
        "",
        f"Twins: `{twins}` (read, not trained); written {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC by "
        f"`python -m benchmarks.bench_inspect_error_budget`; {load_at_end} at the end. Vertices: those the `mesh` map calls "
        "seen and the truth reaches (as in inspect_truth.md). Each cell: median / p90 in pixels at the object (each vertex "
        "over its own pixel footprint), then in mm. Parts: see the module's docstring.",
        "",
        "## Error budget",
        "",
        *budget_table(rows),
        "",
        "## Cameras, bias and the uncertainty",
        "",
        "RMS reprojection (px) of 2,000 true-surface points through the twin's refined cameras (and through the capture's "
        "recorded ones) against the true cameras, as they are and after the one Sim(3) that best explains all of them: the "
        "rest is each camera's own error, which no single surface can fit in every view. Bias: the map's median signed error. "
        "r(U, error): Pearson r of the reported uncertainty against |error|.",
        "",
        *camera_table(rows),
        "",
        "## Where the error lies",
        "",
        "Each cell: the bin's share of the vertices / its median error (px) / its share of the p90 tail (vertices above the "
        "scene's 90th percentile).",
        "",
    ]
    for key in ("views", "best angle deg", "most oblique seeing view deg", "outline in views", "wall thickness px", "uncertainty tercile"):
        text += [*where_table(rows, key), ""]
    if reading:
        text += ["## Reading (written by hand, `--reading`)", "", reading, ""]
    out = "\n".join(text)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(out)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("twins", type=Path, help="Directory with one twin per scene: TWINS/<scene>/twin.json")
    ap.add_argument(
        "--data-dir", type=Path, default=DATA, help="a dataset laid out as rig_scenes (DIR/scenes/<scene>), e.g. rig_scenes_640"
    )
    ap.add_argument("--scenes", default="", help="Comma-separated scene names (default: every scene with a twin).")
    ap.add_argument("--out", type=Path, default=RESULTS / "inspect_error_budget.md")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows as JSON here")
    ap.add_argument("--reading", type=Path, default=None, help="a Markdown file whose text closes the results (the reading)")
    args = ap.parse_args()
    if not args.data_dir.exists():
        raise SystemExit(f"needs the shared data folder ({args.data_dir} is absent)")
    scenes = [s for s in args.scenes.split(",") if s] or sorted(p.name for p in (args.data_dir / "scenes").iterdir())
    rows = []
    for scene in scenes:
        if not (args.twins / scene / "twin.json").exists():
            print(f"{scene}: no twin in {args.twins / scene}, skipped")
            continue
        row = scene_budget(scene, args.twins / scene, args.data_dir)
        print(json.dumps(row), flush=True)
        rows.append(row)
    if not rows:
        raise SystemExit(f"no twins found under {args.twins}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    reading = args.reading.read_text() if args.reading else ""
    print(write_markdown(rows, args.twins, f"1-min {load_line()}", reading, args.out))


if __name__ == "__main__":
    main()

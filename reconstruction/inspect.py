"""Inspection: where a twin's surface departs from its CAD model, by how much, and how sure the rig can be.

Deviation. Every CAD vertex gets the signed distance from the CAD surface to the twin's deformed
surface along the CAD's outward vertex normal, in millimetres: positive where the part stands out of
its drawing (material added, a bulge), negative where it lies inside it (a dent, material missing).
The twin's `mesh_deformed` is the CAD mesh with its vertices moved by the deformation field; the
deviation is read where the CAD vertex's normal line meets the deformed surface (`line_deviation`),
not from the vertex's own move, which also slides along the surface. Meshes that do not correspond
vertex by vertex, and reference surfaces (a scan, the truth of a benchmark), are measured the same way.
The map is then aligned: the small rigid motion (a similarity on a rig of unknown scale) that best fits the
seen surface is taken out of it (`best_fit_surface`), since where a loose part lies against its CAD
frame is placement, not shape; the motion removed is reported beside the map.

Visibility. A vertex is seen by a training camera when it projects inside the image, its normal turns
at most `max_angle_deg` away from the camera's line of sight, and nothing of the twin's surface lies in
front of it (a z-buffer of the deformed mesh). Where no camera sees the surface, the twin there is the
CAD moved only by the field's smooth continuation: it is reported unseen, never in tolerance. Unseen
surface that no camera even has in view (inside its image and within the angle, whatever hides it: an
underside above which all cameras stand) is reported apart: that share is the rig's coverage, which
another capture of the same part would not change; the rest was hidden by the part itself.

Uncertainty. Each seen vertex carries an expanded (k = 2) uncertainty of its deviation, from two sources: where
the views place it (`projection_sigma`: a move along the normal shows in a view only across the line of sight,
by sin(angle) / pixel footprint pixels per millimetre; the best view decides), and
how far the map departs from a smooth surface around it (`local_fit_residual`).

Verdict. FAIL when a seen vertex departs from the tolerance by more than its uncertainty (the worst is named
with its part and position); else UNCERTAIN when more than `max_unseen_pct` of the surface area is unseen;
else UNCERTAIN when a seen vertex's uncertainty straddles the tolerance (those vertices are named); else PASS:
every seen vertex lies inside the tolerance by more than its uncertainty. Exit codes for a PLC: PASS 0,
FAIL 1, UNCERTAIN 3 (too much unseen: another capture can help), 4 (UNCERTAIN: the surface is covered but some
vertex lies within its uncertainty of the tolerance: a finer measurement decides); 2 stays "could not
inspect", as for every cadsplat command.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numba
import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from calibration.camera import Camera, project_points
from reconstruction.mesh_raster import rasterize_mesh
from reconstruction.splats import face_areas_normals

if TYPE_CHECKING:
    from reconstruction.mesh_io import MeshParts
    from reconstruction.twin import Twin

MM_PER_M = 1000.0
MAX_ANGLE_DEG = 75.0  # beyond this the camera looks along the surface: it cannot place it
EXIT_CODES = {"PASS": 0, "FAIL": 1, "UNCERTAIN": 3}
EXIT_NEAR_TOLERANCE = 4  # UNCERTAIN with the surface covered: a vertex's uncertainty straddles the tolerance
# One view's 1-sigma placement of a surface point across its line of sight, in pixels: half a pixel, the outline
# of a binary mask. One value for every part; how many true errors fall inside the k = 2 uncertainty it gives
# on the rig scenes is in benchmarks/results/inspect_truth.md.
SIGMA_PX = 0.5
COVERAGE_K = 2.0  # the uncertainty written is the expanded one, k = 2 (GUM): about 95 % coverage
MIN_SIN = float(np.sin(np.radians(10.0)))  # a view looking straight down the normal still places the point by its texture
RESIDUAL_NEIGHBOURS = 16  # seen vertices on the vertex's side the local fit residual is taken over (twice as many are looked at)
BEST_FIT_KINDS = ("rigid", "similarity")
# The best fit stops when a step moves the surface by less than these (a hundredth of any pixel here).
BEST_FIT_TOL_DEG = 1e-3
BEST_FIT_TOL_MM = 1e-3
BEST_FIT_MAX_STEPS = 20
BEST_FIT_FRACTIONS = (1.0, 0.5, 0.25, 0.125)  # of a step tried in turn, until one lowers the squares
NAMED_VERTICES = 5  # straddling vertices an UNCERTAIN line names (the JSON lists them all)
_NEAR = 1e-6


# ---------------------------------------------------------------------------------------- geometry


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals [V, 3] of `vertices` [V, 3], `faces` [F, 3], turned outward.

    Outward: the winding is flipped when the mesh's signed volume is negative (an inside-out export).
    A vertex no face uses gets +z.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    areas, normals = face_areas_normals(v, f)
    acc = np.zeros_like(v)
    for k in range(3):
        np.add.at(acc, f[:, k], normals * areas[:, None])
    tri = v[f]
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    out = np.where(norm > 0, acc / np.where(norm > 0, norm, 1.0), [0.0, 0.0, 1.0])
    return -out if volume < 0 else out


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Surface area each vertex stands for [V]: a third of every face around it (mesh units squared)."""
    areas, _ = face_areas_normals(vertices, faces)
    out = np.zeros(len(vertices))
    for k in range(3):
        np.add.at(out, np.asarray(faces, np.int64)[:, k], areas / 3.0)
    return out


def vertex_parts(num_vertices: int, faces: np.ndarray, face_part: np.ndarray) -> np.ndarray:
    """Part label of every vertex [V] from its faces' (`face_part` [F]); -1 for a vertex no face uses."""
    out = np.full(num_vertices, -1, np.int64)
    for k in range(3):
        out[np.asarray(faces, np.int64)[:, k]] = face_part
    return out


@numba.njit(cache=True, nogil=True)
def _line_hits(origins, dirs, verts, faces, max_t, out):
    """Signed distance along each line to the nearest crossing of a face that faces the same way (NaN if none)."""
    for i in range(origins.shape[0]):
        ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        best = np.nan
        best_abs = max_t
        for f in range(faces.shape[0]):
            a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
            ax, ay, az = verts[a, 0], verts[a, 1], verts[a, 2]
            e1x, e1y, e1z = verts[b, 0] - ax, verts[b, 1] - ay, verts[b, 2] - az
            e2x, e2y, e2z = verts[c, 0] - ax, verts[c, 1] - ay, verts[c, 2] - az
            # Only a face whose outward side agrees with the line's: never the far wall of a thin part.
            nx, ny, nz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
            if nx * dx + ny * dy + nz * dz <= 0.0:
                continue
            px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
            det = e1x * px + e1y * py + e1z * pz
            if det == 0.0:
                continue
            inv = 1.0 / det
            sx, sy, sz = ox - ax, oy - ay, oz - az
            u = (sx * px + sy * py + sz * pz) * inv
            if u < -1e-9 or u > 1.0 + 1e-9:
                continue
            qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
            w = (dx * qx + dy * qy + dz * qz) * inv
            if w < -1e-9 or u + w > 1.0 + 1e-9:
                continue
            t = (e2x * qx + e2y * qy + e2z * qz) * inv
            if abs(t) <= best_abs:
                best_abs = abs(t)
                best = t
        out[i] = best


def line_deviation(points: np.ndarray, normals: np.ndarray, vertices: np.ndarray, faces: np.ndarray, max_distance: float) -> np.ndarray:
    """Signed distance [P] from each point along its unit normal (both ways) to the surface (`vertices` [V, 3],
    `faces` [F, 3], outward winding), within `max_distance`; NaN where the line meets no face facing its way.

    points [P, 3], normals [P, 3] unit. Positive: the surface lies outside, along the normal.
    """
    out = np.empty(len(points))
    # Writable copies: numba types a read-only array (a twin's mesh as loaded) apart, which would compile the kernel
    # again after the install-time warmup.
    _line_hits(
        np.array(points, np.float64, order="C"),
        np.array(normals, np.float64, order="C"),
        np.array(vertices, np.float64, order="C"),
        np.array(faces, np.int64, order="C"),
        float(max_distance),
        out,
    )
    return out


def normal_deviation(cad_vertices: np.ndarray, cad_normals: np.ndarray, moved_vertices: np.ndarray) -> np.ndarray:
    """Signed move of each vertex along its CAD normal [V]: (moved - cad) . n; all arrays [V, 3]."""
    return np.einsum("ij,ij->i", np.asarray(moved_vertices, np.float64) - cad_vertices, cad_normals)


@dataclass(frozen=True)
class Alignment:
    """A motion a best-fit alignment took out of a map: `kind` ("rigid" or "similarity"), rotation_deg [3] (a rotation
    vector about `centre_mm` [3]), translation_mm [3] and the relative size change `scale` (0 for a rigid fit)."""

    kind: str
    rotation_deg: np.ndarray
    translation_mm: np.ndarray
    centre_mm: np.ndarray
    scale: float

    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "rotation_deg": [round(float(x), 4) for x in self.rotation_deg],
            "translation_mm": [round(float(x), 4) for x in self.translation_mm],
            "centre_mm": [round(float(x), 3) for x in self.centre_mm],
            "scale": round(float(self.scale), 6),
        }


def best_fit_step(points: np.ndarray, normals: np.ndarray, deviation: np.ndarray, weights: np.ndarray, kind: str) -> Alignment:
    """The small motion (rigid, or a similarity: `kind`) whose normal moves best fit `deviation` [V]: the weighted
    (`weights` [V]) least squares of deviation ~ n . (t + w x (p - c)) (+ s n . (p - c)) over points [V, 3] (mm) with
    unit normals [V, 3], to first order in the motion; NaN deviations weigh nothing."""
    if kind not in BEST_FIT_KINDS:
        raise ValueError(f"best-fit alignment must be one of {', '.join(BEST_FIT_KINDS)}, got {kind!r}")
    p = np.asarray(points, np.float64)
    n = np.asarray(normals, np.float64)
    d = np.asarray(deviation, np.float64)
    w = np.where(np.isfinite(d), np.clip(np.asarray(weights, np.float64), 0.0, None), 0.0)
    total = w.sum()
    if total <= 0:
        return Alignment(kind, np.zeros(3), np.zeros(3), p.mean(0) if len(p) else np.zeros(3), 0.0)
    centre = (w[:, None] * p).sum(0) / total
    radius = max(float(np.sqrt((w * ((p - centre) ** 2).sum(1)).sum() / total)), 1e-12)
    x = (p - centre) / radius  # every column about unit size
    cols = [n, np.cross(x, n)] + ([np.einsum("ij,ij->i", n, x)[:, None]] if kind == "similarity" else [])
    basis = np.concatenate(cols, 1)
    sw = np.sqrt(w)
    # The minimum-norm solution leaves a motion the surface cannot show (a sphere's rotation) at zero.
    coef = np.linalg.lstsq(basis * sw[:, None], np.nan_to_num(d) * sw, rcond=1e-9)[0]
    scale = float(coef[6] / radius) if kind == "similarity" else 0.0
    return Alignment(kind, np.degrees(coef[3:6] / radius), coef[:3], centre, scale)


def best_fit_surface(
    cad_vertices: np.ndarray,
    cad_normals: np.ndarray,
    surface_vertices: np.ndarray,
    read: Callable[[np.ndarray], np.ndarray],
    weights: np.ndarray,
    kind: str = "rigid",
    *,
    read_found: Callable[[np.ndarray], np.ndarray] | None = None,
    mm_per_unit: float = MM_PER_M,
) -> tuple[np.ndarray, Alignment, np.ndarray]:
    """`surface_vertices` [S, 3] moved by the rigid motion (or similarity, `kind`) that best fits the surface onto the
    CAD (points [V, 3], unit normals [V, 3], same units as the surface; `mm_per_unit` to mm) along the CAD normals.
    `read(vertices)` gives the surface's deviation [V] along them (NaN where it has none); `read_found`, where it
    differs, only where the surface is found along the normal line (a guessed value is no reading to fit); `weights`
    [V] (the seen area) say which vertices speak.

    A free part lies on the rig however it fell: where it lies against its CAD frame is placement, not shape, and
    the registration that placed it could only fit it. So a map is read after a best fit, as inspection software
    aligns a scan before it colours it: by least squares (their Gaussian best fit), so a dent pulls the part towards
    it by its share of the seen area. Robust weights were measured and not kept: on thin parts they let the fit turn
    about the long axis (benchmarks/results/inspect_truth.md). A step fits the motion to first order and moves the
    surface by it; the surface is read again, since a motion of a few degrees slides a curved surface along the
    normal lines by more than the first order says. A step is taken only as far as it lowers the weighted squares of
    `read` (a vertex with no reading counts as the line's reach): a part whose shape holds the motion weakly (a ball
    beside a block of a few vertices) is never turned away from its drawing.
    Returns the moved vertices, the whole motion removed and each vertex's weight in the fit [V] (0 where the
    surface was not found), by which a reference surface can be aligned the same way.
    """
    cad_v = np.asarray(cad_vertices, np.float64)
    start = np.asarray(surface_vertices, np.float64)
    read_found = read if read_found is None else read_found
    base = np.clip(np.asarray(weights, np.float64), 0.0, None)
    reach_mm = 0.1 * float(np.linalg.norm(cad_v.max(0) - cad_v.min(0))) * mm_per_unit

    def cost(vertices: np.ndarray) -> float:
        d = np.nan_to_num(read(vertices) * mm_per_unit, nan=reach_mm)
        return float((base * np.minimum(d * d, reach_mm * reach_mm)).sum())

    moved, current = start.copy(), cost(start)
    fit_weight = np.zeros(len(cad_v))
    for _ in range(BEST_FIT_MAX_STEPS):
        deviation = read_found(moved) * mm_per_unit
        speaks = (base > 0) & np.isfinite(deviation)
        if not speaks.any():
            break
        fit_weight = np.where(speaks, base, 0.0)
        step = best_fit_step(cad_v * mm_per_unit, cad_normals, deviation, fit_weight, kind)
        for fraction in BEST_FIT_FRACTIONS:
            rotation = Rotation.from_rotvec(-fraction * np.radians(step.rotation_deg)).as_matrix()
            centre = step.centre_mm / mm_per_unit
            trial = ((moved - centre) @ rotation.T) * (1.0 - fraction * step.scale) + centre - fraction * step.translation_mm / mm_per_unit
            trial_cost = cost(trial)
            if trial_cost < current:
                moved, current = trial, trial_cost
                break
        else:
            break
        if (
            fraction * np.linalg.norm(step.rotation_deg) < BEST_FIT_TOL_DEG
            and fraction * np.linalg.norm(step.translation_mm) < BEST_FIT_TOL_MM
        ):
            break
    return moved, _motion_between(start, moved, kind, mm_per_unit), fit_weight


def _motion_between(before: np.ndarray, after: np.ndarray, kind: str, mm_per_unit: float) -> Alignment:
    """The similarity taking `before` [S, 3] to `after` (exact, as composed from the steps; Umeyama), as the motion
    the alignment removed: rotation vector, translation at the centroid, relative scale."""
    cb, ca = before.mean(0), after.mean(0)
    u, sig, vt = np.linalg.svd((after - ca).T @ (before - cb))
    fix = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ fix @ vt
    scale = float((sig * np.diag(fix)).sum() / max(((before - cb) ** 2).sum(), 1e-300)) if kind == "similarity" else 1.0
    # Removed = the inverse of what was applied to the surface.
    return Alignment(
        kind,
        -Rotation.from_matrix(rotation).as_rotvec(degrees=True),
        (cb - ca) * mm_per_unit,
        cb * mm_per_unit,
        1.0 / scale - 1.0 if kind == "similarity" else 0.0,
    )


def surface_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Distance [P] from each of `points` [P, 3] to the closest point of the mesh (`vertices` [V, 3], `faces` [F, 3])."""
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
    return trimesh.proximity.closest_point(mesh, np.asarray(points, np.float64))[1]


# ---------------------------------------------------------------------------------------- visibility


@dataclass(frozen=True)
class Visibility:
    """Which cameras see each vertex: `seen` [C, V] bool, `views` [V] count, `best_angle_deg` [V] (the smallest
    angle between the normal and a seeing camera's line of sight; NaN where no camera sees the vertex)."""

    seen: np.ndarray
    views: np.ndarray
    best_angle_deg: np.ndarray
    in_view: np.ndarray  # [V] cameras that have the vertex in their image within the angle, occluded or not
    cos: np.ndarray  # [C, V] cosine between the normal and the direction to each camera
    footprint: np.ndarray  # [C, V] a pixel's size at the point in each camera (units of the points per pixel)


def point_visibility(
    points: np.ndarray,
    normals: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    cameras: Sequence[Camera],
    *,
    max_angle_deg: float = MAX_ANGLE_DEG,
) -> Visibility:
    """Visibility from `cameras` of `points` [P, 3] with unit `normals` [P, 3] lying on the mesh (`vertices`
    [V, 3], `faces` [F, 3]) that may hide them.

    A point is seen when it projects inside the image, its normal is within `max_angle_deg` of the
    direction to the camera, and the z-buffer at its pixel is not nearer than the point by more than
    the surface's own depth change across a pixel at that slant.
    """
    p = np.asarray(points, np.float64)
    cos_min = np.cos(np.radians(max_angle_deg))
    seen = np.zeros((len(cameras), len(p)), bool)
    in_view = np.zeros(len(p), np.int64)
    cos_best = np.full(len(p), -1.0)
    cos_all = np.zeros((len(cameras), len(p)))
    footprint_all = np.zeros((len(cameras), len(p)))
    for i, cam in enumerate(cameras):
        depth, _, _ = rasterize_mesh(vertices, faces, cam)
        uv, z = project_points(p, cam.K, cam.viewmat, near=_NEAR)
        to_cam = cam.center - p
        cos = np.einsum("ij,ij->i", normals, to_cam) / np.maximum(np.linalg.norm(to_cam, axis=1), 1e-300)
        px = np.floor(np.nan_to_num(uv, nan=-1.0)).astype(np.int64)
        inside = (z > _NEAR) & (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
        zbuf = np.full(len(p), -np.inf)
        zbuf[inside] = depth[px[inside, 1], px[inside, 0]]
        # A pixel centre is up to 0.71 px from the point: the point's own surface may lie that far times
        # tan(angle) nearer; one more pixel's worth covers the neighbouring faces' kinks.
        footprint = np.abs(z) / cam.K[0, 0]
        cos_all[i], footprint_all[i] = cos, np.abs(z) / (0.5 * (cam.K[0, 0] + cam.K[1, 1]))
        tan = np.sqrt(np.maximum(1.0 - cos * cos, 0.0)) / np.maximum(cos, cos_min)
        unoccluded = zbuf >= z - footprint * (1.0 + 2.0 * tan)
        facing = inside & (cos >= cos_min)
        seen[i] = facing & unoccluded
        in_view += facing
        cos_best = np.where(seen[i], np.maximum(cos_best, cos), cos_best)
    views = seen.sum(0)
    best = np.where(views > 0, np.degrees(np.arccos(np.clip(cos_best, -1.0, 1.0))), np.nan)
    return Visibility(seen, views, best, in_view, cos_all, footprint_all)


# ---------------------------------------------------------------------------------------- uncertainty


def projection_sigma(seen: np.ndarray, cos: np.ndarray, footprint: np.ndarray, sigma_px: float = SIGMA_PX) -> np.ndarray:
    """1-sigma [V] of each point's place along its normal from the views that see it (units of `footprint`); NaN unseen.

    seen [C, V] bool, cos [C, V] (normal against the direction to the camera), footprint [C, V] (a pixel's size at the
    point). A move d along the normal shifts the point's image in view c by d sin(angle_c) / footprint_c pixels (its
    part along the line of sight does not show); each view places the image to `sigma_px`. The point is as sure as
    its best view makes it: the views' information is not summed, since one fit (one deformation field, one set of
    poses) explains them all and their errors are not independent. sin is floored at `MIN_SIN`: a view along the
    normal still places a textured point.
    """
    sin = np.maximum(np.sqrt(np.clip(1.0 - np.asarray(cos) ** 2, 0.0, 1.0)), MIN_SIN)
    info = np.where(seen, (sin / np.maximum(footprint, 1e-300)) ** 2, 0.0).max(0, initial=0.0)
    return np.where(info > 0, sigma_px / np.sqrt(np.maximum(info, 1e-300)), np.nan)


def local_fit_residual(
    points: np.ndarray, normals: np.ndarray, values: np.ndarray, valid: np.ndarray, k: int = RESIDUAL_NEIGHBOURS
) -> np.ndarray:
    """RMS residual [P] of a quadric fit (value = a + b u + c w + d u^2 + e uw + f w^2 over the tangent plane) of
    `values` [P] on each valid
    point's k nearest valid neighbours on its own side of the surface (points [P, 3], unit normals [P, 3], valid [P]
    bool); NaN where not valid or too few neighbours face its way.

    Neighbours whose normal turns more than 60 deg from the point's are left out: across a thin part's edge they lie
    on the other wall, whose deviation is another. A quadric follows a smooth bump or dent (a real departure, to be
    measured, not doubted); its six parameters are taken out of the degrees of freedom, so a smooth map gives 0
    and a noisy one its noise.
    """
    out = np.full(len(points), np.nan)
    idx = np.flatnonzero(valid)
    k = min(2 * k, idx.size)
    if k < 7:
        return out
    from scipy.spatial import cKDTree

    p = np.asarray(points, np.float64)[idx]
    _, nb = cKDTree(p).query(p, k=k)
    n = np.asarray(normals, np.float64)[idx]
    weight = (np.einsum("nd,nkd->nk", n, n[nb]) >= 0.5).astype(np.float64)
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    rel = p[nb] - p[:, None, :]  # [n, k, 3]
    u, w = np.einsum("nkd,nd->nk", rel, t1), np.einsum("nkd,nd->nk", rel, t2)
    design = np.stack([np.ones(rel.shape[:2]), u, w, u * u, u * w, w * w], -1)
    y = np.asarray(values, np.float64)[idx][nb]
    wd = design * weight[..., None]
    coef = np.einsum("nij,nj->ni", np.linalg.pinv(wd), y * weight)
    resid = (y - np.einsum("nkj,nj->nk", design, coef)) * weight
    dof = weight.sum(1) - 6
    out[idx] = np.where(dof >= 1, np.sqrt((resid**2).sum(1) / np.maximum(dof, 1)), np.nan)
    return out


def expanded_uncertainty(sigma_projection: np.ndarray, residual: np.ndarray, k: float = COVERAGE_K) -> np.ndarray:
    """k times the root sum of squares of the two 1-sigma sources [V] (NaN where either is)."""
    return k * np.sqrt(np.asarray(sigma_projection) ** 2 + np.asarray(residual) ** 2)


# ---------------------------------------------------------------------------------------- inspection


@dataclass(frozen=True)
class Inspection:
    """Per-vertex findings on the CAD mesh, object frame, millimetres.

    vertices_mm [V, 3] (CAD positions), deviation_mm [V] (signed, along the outward CAD normal; NaN where
    the twin's surface could not be found along it), views [V], best_angle_deg [V] (NaN unseen),
    area_mm2 [V], part [V] (index into part_names); in_view [V] (cameras that have the vertex in view,
    occluded or not; None when not known). uncertainty_mm [V]: the deviation's expanded (k = 2) uncertainty,
    NaN unseen (None: the map is taken as exact); footprint_mm [V]: a pixel's size at the vertex, median over the
    views that see it; residual_mm [V]: the local fit residual that entered the uncertainty; alignment: the best-fit
    motion taken out of the deviation (None: read in the CAD frame as the twin placed it); fit_weight_mm2 [V]: each
    vertex's weight in it (its seen area; 0 outside it).
    """

    vertices_mm: np.ndarray
    deviation_mm: np.ndarray
    views: np.ndarray
    best_angle_deg: np.ndarray
    area_mm2: np.ndarray
    part: np.ndarray
    part_names: list[str]
    in_view: np.ndarray | None = None
    uncertainty_mm: np.ndarray | None = None
    footprint_mm: np.ndarray | None = None
    residual_mm: np.ndarray | None = None
    alignment: Alignment | None = None
    fit_weight_mm2: np.ndarray | None = None

    @property
    def seen(self) -> np.ndarray:
        """[V] bool: a camera saw the vertex, the twin's surface was found along its normal, and a face uses it."""
        return (self.views > 0) & np.isfinite(self.deviation_mm) & (self.part >= 0)

    def unseen_pct(self, mask: np.ndarray | None = None) -> float:
        """Share of the surface area (of the vertices in `mask`, default all) that no camera saw, in %."""
        m = np.ones(len(self.views), bool) if mask is None else mask
        total = self.area_mm2[m].sum()
        return 0.0 if total <= 0 else float(100.0 * self.area_mm2[m & ~self.seen].sum() / total)

    def out_of_view_pct(self, mask: np.ndarray | None = None) -> float | None:
        """Share of the surface area (of the vertices in `mask`) unseen because no camera has it in view at all, in %
        (the rig's coverage); None when `in_view` is not known."""
        if self.in_view is None:
            return None
        m = np.ones(len(self.views), bool) if mask is None else mask
        total = self.area_mm2[m].sum()
        return 0.0 if total <= 0 else float(100.0 * self.area_mm2[m & ~self.seen & (self.in_view == 0)].sum() / total)


def _read_deviation(
    cad_v: np.ndarray, normals: np.ndarray, surface_v: np.ndarray, surface_f: np.ndarray, same: bool, reach: float, guess: bool = True
) -> np.ndarray:
    """[V] the deviation of the surface from the CAD along each CAD vertex's normal line (model units).

    Read where the line meets the surface, as a reference surface is measured: when the surface is the CAD with moved
    vertices (`same`), a vertex's own move also slides along the surface, which is not a deviation
    (benchmarks/results/inspect_error_budget.md). There a hit is the vertex's own surface only within its slide of
    the projected move (the surface tilted at most 45 degrees); beyond that, or with no hit, the line found another
    sheet and the projected move stands (NaN with `guess` False: the surface was not found there)."""
    line = line_deviation(cad_v, normals, surface_v, surface_f, reach)
    if not same:
        return line
    moved = normal_deviation(cad_v, normals, surface_v)
    slide = np.linalg.norm(surface_v - cad_v - moved[:, None] * normals, axis=1)
    return np.where(np.abs(np.nan_to_num(line, nan=np.inf) - moved) <= slide, line, moved if guess else np.nan)


def inspect_meshes(
    cad_vertices: np.ndarray,
    cad_faces: np.ndarray,
    face_part: np.ndarray,
    part_names: Sequence[str],
    deformed_vertices: np.ndarray,
    deformed_faces: np.ndarray,
    cameras: Sequence[Camera],
    *,
    masks: Sequence[np.ndarray] | None = None,
    mm_per_unit: float = MM_PER_M,
    max_angle_deg: float = MAX_ANGLE_DEG,
    best_fit: str | None = "rigid",
) -> Inspection:
    """Deviation of the deformed surface from the CAD and its visibility from `cameras` (object frame).

    The CAD mesh (`cad_vertices` [V, 3], `cad_faces` [F, 3], `face_part` [F]) and the deformed mesh are in the
    same units (`mm_per_unit` converts them; the twin format is in metres). The CAD normal line is cast onto the
    deformed surface (up to a tenth of the CAD's bounding diagonal); when the deformed mesh is the CAD mesh with
    moved vertices (same faces), a vertex whose line meets no facing face takes its move projected on the normal.
    Visibility is judged on the deformed surface, the one the cameras photographed. With `masks` (one [H, W] bool
    per camera, at the camera's own resolution or any other), the map is corrected where the masks' outlines place
    the surface more finely (`inspect_silhouette.silhouette_correction`), and the outlines' residual enters the
    uncertainty. The deviation is read after the `best_fit` alignment of the seen surface ("rigid", "similarity"
    where the rig's scale is not known, or None; `best_fit_surface`).
    """
    cad_v = np.asarray(cad_vertices, np.float64)
    normals = vertex_normals(cad_v, cad_faces)
    dv = np.asarray(deformed_vertices, np.float64)
    same = np.shape(dv) == cad_v.shape and np.array_equal(deformed_faces, cad_faces)
    reach = 0.1 * float(np.linalg.norm(cad_v.max(0) - cad_v.min(0)))
    deviation = _read_deviation(cad_v, normals, dv, deformed_faces, same, reach)
    if same:
        vis = point_visibility(dv, vertex_normals(dv, cad_faces), dv, cad_faces, cameras, max_angle_deg=max_angle_deg)
    else:
        # Each CAD vertex where its normal line meets the deformed surface (the CAD place where it missed).
        on_twin = cad_v + np.nan_to_num(deviation)[:, None] * normals
        vis = point_visibility(on_twin, normals, dv, deformed_faces, cameras, max_angle_deg=max_angle_deg)
    areas = vertex_areas(cad_v, cad_faces)
    alignment, fit_weight = None, None
    if best_fit is not None:
        # Visibility stays that of the surface the cameras photographed; the deviation is read on the aligned one.
        weights = np.where((vis.views > 0) & np.isfinite(deviation), areas, 0.0)
        aligned, alignment, fit_weight = best_fit_surface(
            cad_v,
            normals,
            dv,
            lambda v: _read_deviation(cad_v, normals, v, deformed_faces, same, reach),
            weights,
            best_fit,
            # Fitted only where the surface is found along the normal line: a projected move is a guess, not a reading.
            read_found=lambda v: _read_deviation(cad_v, normals, v, deformed_faces, same, reach, guess=False),
            mm_per_unit=mm_per_unit,
        )
        deviation = _read_deviation(cad_v, normals, aligned, deformed_faces, same, reach)
    rim_residual = np.full(len(cad_v), np.nan)
    if masks is not None:
        from scipy.spatial import cKDTree

        from reconstruction.inspect_silhouette import silhouette_correction

        correction, rim_residual, _ = silhouette_correction(dv, deformed_faces, vertex_normals(dv, deformed_faces), cameras, masks)
        if not same:
            nearest = cKDTree(dv).query(on_twin)[1]
            correction, rim_residual = correction[nearest], rim_residual[nearest]
        deviation = deviation + correction
    seen = (vis.views > 0) & np.isfinite(deviation)
    sigma = projection_sigma(vis.seen, vis.cos, vis.footprint)
    residual = local_fit_residual(cad_v, normals, deviation, seen)
    # A seen vertex without enough neighbours on its side of the surface takes the map's typical residual.
    typical = float(np.nanmedian(residual)) if np.isfinite(residual).any() else 0.0
    residual = np.where(seen & ~np.isfinite(residual), typical, residual)
    residual = np.where(np.isfinite(rim_residual), np.sqrt(residual**2 + rim_residual**2), residual)
    footprint = np.nanmedian(np.where(vis.seen, vis.footprint, np.nan)[:, seen], 0) if seen.any() else np.zeros(0)
    footprint_all = np.full(len(cad_v), np.nan)
    footprint_all[seen] = footprint
    return Inspection(
        vertices_mm=cad_v * mm_per_unit,
        deviation_mm=deviation * mm_per_unit,
        views=vis.views,
        best_angle_deg=vis.best_angle_deg,
        area_mm2=areas * mm_per_unit**2,
        part=vertex_parts(len(cad_v), cad_faces, face_part),
        part_names=list(part_names),
        in_view=vis.in_view,
        uncertainty_mm=np.where(seen, expanded_uncertainty(sigma, residual), np.nan) * mm_per_unit,
        footprint_mm=footprint_all * mm_per_unit,
        residual_mm=residual * mm_per_unit,
        alignment=alignment,
        fit_weight_mm2=None if fit_weight is None else fit_weight * mm_per_unit**2,
    )


def inspect_twin(
    twin: Twin,
    masks: Sequence[np.ndarray] | None = None,
    *,
    cad: MeshParts | None = None,
    deformed: MeshParts | None = None,
    max_angle_deg: float = MAX_ANGLE_DEG,
    aligned: bool = True,
) -> Inspection:
    """`inspect_meshes` on a loaded twin: its CAD and deformed meshes (metres; `cad`, `deformed` when already read
    from it) from its trained cameras, refined by the capture's `masks` (one [H, W] bool per twin camera, in
    `twin.cameras` order, at the capture's resolution) when given. The map is aligned by the best rigid fit, or by a
    similarity where the twin's rig has no metric scale (`alignment_kind`); `aligned` False reads it in the CAD frame
    as the twin placed it."""
    cad = twin.load_mesh_cad() if cad is None else cad
    deformed = twin.load_mesh_deformed() if deformed is None else deformed
    return inspect_meshes(
        cad.vertices,
        cad.faces,
        cad.face_part,
        cad.part_names,
        deformed.vertices,
        deformed.faces,
        [c.camera for c in twin.cameras],
        masks=masks,
        max_angle_deg=max_angle_deg,
        best_fit=alignment_kind(twin) if aligned else None,
    )


def alignment_kind(twin: Twin) -> str:
    """ "rigid" when the twin's rig is metric (a part larger than its drawing is a deviation), else "similarity" (no
    photograph of an unscaled rig tells the part's size); a twin that does not record it is taken as metric."""
    return "rigid" if twin.training.get("inputs", {}).get("metric", True) else "similarity"


# ---------------------------------------------------------------------------------------- report


@dataclass(frozen=True)
class PartReport:
    """One part's findings (millimetres, object frame). Deviation figures are over its seen vertices;
    `worst_mm` is the signed deviation of largest magnitude, at `worst_at_mm` (None when nothing was seen).
    Uncertainty: `unseen_pct` and `single_view_pct` of the part's area (`out_of_view_pct` of it unseen because no
    camera has it in view: the rig's coverage; None when not known), and over its seen vertices the median
    number of views and of the best angle between normal and line of sight."""

    name: str
    vertices: int
    area_mm2: float
    unseen_pct: float
    single_view_pct: float
    views_median: float | None
    best_angle_median_deg: float | None
    worst_mm: float | None
    worst_at_mm: tuple[float, float, float] | None
    mean_mm: float | None
    p95_abs_mm: float | None
    out_of_tolerance_pct: float
    out_of_view_pct: float | None = None

    def to_dict(self) -> dict:
        """JSON-ready: positions as lists."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in ((k, getattr(self, k)) for k in self.__dataclass_fields__)}


def part_reports(insp: Inspection, tolerance_mm: float) -> list[PartReport]:
    """Per-part summary of `insp`; `out_of_tolerance_pct` is the seen area beyond `tolerance_mm`, % of the part."""
    out = []
    for p, name in enumerate(insp.part_names):
        m = insp.part == p
        s = m & insp.seen
        area = float(insp.area_mm2[m].sum())
        worst = worst_at = mean = p95 = views = angle = None
        bad = 0.0
        single = 100.0 * float(insp.area_mm2[s & (insp.views == 1)].sum()) / max(area, 1e-300)
        if s.any():
            views, angle = float(np.median(insp.views[s])), float(np.median(insp.best_angle_deg[s]))
            d = insp.deviation_mm[s]
            i = int(np.argmax(np.abs(d)))
            worst, worst_at = float(d[i]), tuple(float(x) for x in insp.vertices_mm[s][i])
            mean, p95 = float(d.mean()), float(np.percentile(np.abs(d), 95))
            bad = 100.0 * float(insp.area_mm2[s][np.abs(d) > tolerance_mm].sum()) / max(area, 1e-300)
        out.append(
            PartReport(
                name, int(m.sum()), area, insp.unseen_pct(m), single, views, angle, worst, worst_at, mean, p95, bad, insp.out_of_view_pct(m)
            )
        )
    return out


@dataclass(frozen=True)
class NamedVertex:
    """A vertex a verdict names: its index on the CAD mesh, part, signed deviation and uncertainty (mm), position (mm)."""

    vertex: int
    part: str | None
    deviation_mm: float
    uncertainty_mm: float
    at_mm: tuple[float, float, float]

    def to_dict(self) -> dict:
        return {
            "vertex": self.vertex,
            "part": self.part,
            "deviation_mm": self.deviation_mm,
            "uncertainty_mm": self.uncertainty_mm,
            "at_mm": list(self.at_mm),
        }

    def text(self) -> str:
        x, y, z = self.at_mm
        return (
            f"vertex {self.vertex} of part '{self.part}' {self.deviation_mm:+.2f} +-{self.uncertainty_mm:.2f} mm "
            f"at ({x:.1f}, {y:.1f}, {z:.1f}) mm"
        )


@dataclass(frozen=True)
class Verdict:
    """The one-line verdict and its exit code (`EXIT_CODES`, `EXIT_NEAR_TOLERANCE`); `part`, `deviation_mm`, `at_mm`
    name the worst seen vertex, `max_abs_mm` its magnitude and `uncertainty_mm` its uncertainty (None when nothing
    was seen). `reason`: why (None for PASS; "out of tolerance"; "unseen"; "near tolerance"). `straddling`: every
    seen vertex whose uncertainty straddles the tolerance, largest |deviation| first; `straddling_pct` their
    share of the surface area; `out_pct` the share certainly out of tolerance."""

    status: str
    line: str
    exit_code: int
    tolerance_mm: float
    max_unseen_pct: float
    unseen_pct: float
    max_abs_mm: float | None
    part: str | None
    deviation_mm: float | None
    at_mm: tuple[float, float, float] | None
    out_of_view_pct: float | None = None
    reason: str | None = None
    uncertainty_mm: float | None = None
    straddling: tuple[NamedVertex, ...] = ()
    straddling_pct: float = 0.0
    out_pct: float = 0.0

    def to_dict(self) -> dict:
        """JSON-ready: positions as lists, named vertices as objects."""
        out = {}
        for k in self.__dataclass_fields__:
            v = getattr(self, k)
            out[k] = [x.to_dict() for x in v] if k == "straddling" else list(v) if isinstance(v, tuple) else v
        return out


def _beside(value: float, limit: float, digits: int = 0) -> str:
    """value to `digits` decimals, or one more where that would print the limit it is judged against (25.3 % against
    25 %, 1.48 mm against 1.5 mm)."""
    text = f"{value:.{digits}f}"
    return f"{value:.{digits + 1}f}" if text == f"{limit:.{digits}f}" and value != limit else text


def tolerance_calls(deviation_mm: np.ndarray, uncertainty_mm: np.ndarray, tolerance_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(certainly out [V], straddling [V]) bool for deviations [V] with their uncertainties [V] (0 where NaN):
    out when |d| exceeds the tolerance by more than u; straddling when neither out nor inside it by more than u."""
    d = np.abs(np.asarray(deviation_mm, np.float64))
    u = np.nan_to_num(np.asarray(uncertainty_mm, np.float64))
    out = d - u > tolerance_mm
    return out, ~out & (d + u >= tolerance_mm)


def _named(insp: Inspection, i: int, u: np.ndarray) -> NamedVertex:
    return NamedVertex(
        int(i),
        insp.part_names[insp.part[i]] if insp.part[i] >= 0 else None,
        float(insp.deviation_mm[i]),
        float(u[i]),
        tuple(float(x) for x in insp.vertices_mm[i]),
    )


def verdict(insp: Inspection, tolerance_mm: float, max_unseen_pct: float) -> Verdict:
    """FAIL if a seen vertex departs from `tolerance_mm` by more than its uncertainty (the worst of those is named);
    else UNCERTAIN if more than `max_unseen_pct` of the area is unseen (exit 3); else UNCERTAIN if a seen vertex's
    uncertainty straddles the tolerance (exit 4, the largest named); else PASS. A twin nobody saw any of is UNCERTAIN,
    whatever `max_unseen_pct` says. An inspection without uncertainties is taken as exact."""
    if not tolerance_mm > 0:
        raise ValueError(f"the tolerance must be a positive number of millimetres, got {tolerance_mm}")
    unseen = insp.unseen_pct()
    out_of_view = insp.out_of_view_pct()
    # Unseen surface that no camera has in view is the rig's coverage: said apart, so an operator knows whether
    # another capture could help.
    why = "" if out_of_view is None or unseen < 0.5 else f" ({out_of_view:.0f} % in no camera's view)"
    seen = insp.seen
    u = np.zeros(len(seen)) if insp.uncertainty_mm is None else np.where(seen, np.nan_to_num(insp.uncertainty_mm), 0.0)
    out, straddle = tolerance_calls(np.where(seen, insp.deviation_mm, 0.0), u, tolerance_mm)
    out &= seen
    straddle &= seen
    area = max(float(insp.area_mm2.sum()), 1e-300)
    straddling = tuple(
        _named(insp, i, u) for i in np.flatnonzero(straddle)[np.argsort(-np.abs(insp.deviation_mm[straddle]), kind="stable")]
    )
    worst = part = at = unc = None
    if seen.any():
        # The worst vertex: among those certainly out when any is, else among all seen.
        pool = out if out.any() else seen
        i = int(np.argmax(np.where(pool, np.abs(insp.deviation_mm), -np.inf)))
        worst, at, unc = float(insp.deviation_mm[i]), tuple(float(x) for x in insp.vertices_mm[i]), float(u[i])
        part = insp.part_names[insp.part[i]] if insp.part[i] >= 0 else None
    pm = "" if insp.uncertainty_mm is None or unc is None else f" +-{unc:.2f}"
    tol = f"{tolerance_mm:g} mm"
    out_pct = 100.0 * float(insp.area_mm2[out].sum()) / area
    straddling_pct = 100.0 * float(insp.area_mm2[straddle].sum()) / area
    if out.any():
        status, reason, code = "FAIL", "out of tolerance", EXIT_CODES["FAIL"]
        line = f"FAIL part '{part}' {'+' if worst > 0 else '-'}{_beside(abs(worst), tolerance_mm, 1)}{pm} mm at ({at[0]:.1f}, {at[1]:.1f}, {at[2]:.1f}) mm"
        if insp.uncertainty_mm is not None:
            line += f"; {_beside(out_pct, 0.0, 0)} % of the surface out of tolerance beyond its uncertainty"
    elif worst is None or unseen > max_unseen_pct:
        status, reason, code = "UNCERTAIN", "unseen", EXIT_CODES["UNCERTAIN"]
        seen_part = (
            "" if worst is None else f"; seen surface within tolerance, max {_beside(abs(worst), tolerance_mm, 1)}{pm} mm (tolerance {tol})"
        )
        line = f"UNCERTAIN {_beside(unseen, max_unseen_pct)} % of the surface unseen{why}{seen_part}"
    elif straddling:
        status, reason, code = "UNCERTAIN", "near tolerance", EXIT_NEAR_TOLERANCE
        named = "; ".join(v.text() for v in straddling[:NAMED_VERTICES])
        more = f"; and {len(straddling) - NAMED_VERTICES} more" if len(straddling) > NAMED_VERTICES else ""
        line = (
            f"UNCERTAIN {len(straddling)} seen vertices ({_beside(straddling_pct, 0.0, 1)} % of the surface) lie within their "
            f"uncertainty of the {tol} tolerance: {named}{more}"
        )
    else:
        status, reason, code = "PASS", None, EXIT_CODES["PASS"]
        line = f"PASS max {_beside(abs(worst), tolerance_mm, 1)}{pm} mm (tolerance {tol})" + (
            f", {_beside(unseen, max_unseen_pct)} % of the surface unseen{why}" if unseen >= 0.5 else ""
        )
    return Verdict(
        status,
        line,
        code,
        float(tolerance_mm),
        float(max_unseen_pct),
        unseen,
        None if worst is None else abs(worst),
        part,
        worst,
        at,
        out_of_view,
        reason,
        unc if insp.uncertainty_mm is not None else None,
        straddling,
        straddling_pct,
        out_pct,
    )


# ---------------------------------------------------------------------------------------- pictures

UNSEEN_RGB = np.array([0.35, 0.35, 0.35])


def deviation_colors(deviation_mm: np.ndarray, seen: np.ndarray, range_mm: float) -> np.ndarray:
    """RGB [V, 3] in [0, 1]: the turbo colour map from -`range_mm` (blue, inside the CAD) through 0 (green)
    to +`range_mm` (red, outside), clipped; unseen vertices dark grey."""
    from matplotlib import colormaps

    x = np.clip(0.5 + 0.5 * np.nan_to_num(deviation_mm) / range_mm, 0.0, 1.0)
    rgb = colormaps["turbo"](x)[:, :3]
    return np.where(seen[:, None], rgb, UNSEEN_RGB)


def render_colored_mesh(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, camera: Camera) -> np.ndarray:
    """Straight-alpha RGBA [H, W, 4] float32 of a mesh with per-vertex `colors` [V, 3], shaded by a headlight
    (the interpolated vertex normal against the line of sight) so the shape reads in a flat colour map."""
    _, face_id, bary = rasterize_mesh(vertices, faces, camera)
    hit = face_id >= 0
    f = np.asarray(faces, np.int64)[face_id[hit]]
    w = bary[hit]
    normals = vertex_normals(vertices, faces)
    n = np.einsum("pk,pkd->pd", w, normals[f])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    v = np.asarray(vertices, np.float64)
    p = np.einsum("pk,pkd->pd", w, v[f])
    view = camera.center - p
    shade = 0.35 + 0.65 * np.abs(np.einsum("pd,pd->p", n, view)) / np.maximum(np.linalg.norm(view, axis=1), 1e-12)
    out = np.zeros((camera.height, camera.width, 4), np.float32)
    out[hit, :3] = np.einsum("pk,pkd->pd", w, np.asarray(colors, np.float64)[f]) * shade[:, None]
    out[hit, 3] = 1.0
    return out

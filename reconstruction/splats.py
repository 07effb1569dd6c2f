"""Splats on the CAD surface (paper 3.4): area-weighted samples, face normals, oriented disks.

Each splat keeps the face it was drawn from, its barycentric coordinates and the CAD part of that
face, so a twin can be edited per part and its splats followed through rigid-body simulation.
Means and quaternions are frozen during training; only the deformation field moves the splats.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from calibration.camera import project_points
from reconstruction.gaussians import Gaussians

SH_C0 = 0.28209479177387814  # Y_0^0; 3DGS stores colour = 0.5 + SH_C0 * dc
DISK_FLATTENING = 0.1  # normal-axis scale / tangent scale: thin disks that still rasterize stably


@dataclass
class CanonicalSplats:
    """Gaussians on the CAD surface in the model's canonical frame and where each sits on it (N rows):
    `gaussians` (quats turn local z onto the normal), normals [N, 3] unit, face_index [N] int64,
    barycentrics [N, 3] float32, part_label [N] int64.
    """

    gaussians: Gaussians
    normals: np.ndarray
    face_index: np.ndarray
    barycentrics: np.ndarray
    part_label: np.ndarray

    def __len__(self) -> int:
        return len(self.gaussians)

    @property
    def means(self) -> np.ndarray:
        return self.gaussians.means


def face_areas_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Areas [F] and unit normals [F, 3] (right-hand rule). Zero-area faces get area 0 and normal +z."""
    v = np.asarray(vertices, np.float64)
    tri = v[np.asarray(faces, np.int64)]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(cross, axis=1)
    # Relative threshold: a face is degenerate when its area is negligible against its edge lengths.
    edge = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(1)
    degenerate = ~(norm > 1e-12 * np.maximum(edge * edge, 1e-300))
    normals = np.where(degenerate[:, None], [0.0, 0.0, 1.0], cross / np.where(degenerate, 1.0, norm)[:, None])
    return np.where(degenerate, 0.0, 0.5 * norm), normals


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Area-uniform samples on a triangle mesh: points [n, 3], face index [n], barycentrics [n, 3].

    Degenerate (zero-area) faces are never drawn; a mesh with no area raises ValueError.
    """
    if n <= 0:
        raise ValueError(f"splat count must be positive, got {n}")
    faces = np.asarray(faces, np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError("the mesh has no triangles to put splats on")
    areas, _ = face_areas_normals(vertices, faces)
    total = areas.sum()
    if not (np.isfinite(total) and total > 0):
        raise ValueError("the mesh has zero surface area (all faces are degenerate)")
    face_index = rng.choice(len(faces), size=n, p=areas / total)
    # Uniform on a triangle: fold the unit square onto the lower-left half.
    r = rng.random((n, 2))
    flip = r.sum(1) > 1
    r[flip] = 1 - r[flip]
    bary = np.stack([1 - r[:, 0] - r[:, 1], r[:, 0], r[:, 1]], 1)
    tri = np.asarray(vertices, np.float64)[faces[face_index]]
    points = np.einsum("nk,nkd->nd", bary, tri)
    return points, face_index, bary


def normals_to_quats(normals: np.ndarray) -> np.ndarray:
    """Shortest-arc rotations wxyz [N, 4] taking local +z to each unit normal [N, 3].

    q = normalise(1 + z.n, z x n) = normalise(1 + n_z, -n_y, n_x, 0); at n = -z that vanishes, so
    the half-turn about x (0, 1, 0, 0) is used (any axis perpendicular to z is a shortest arc).
    """
    n = np.asarray(normals, np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    q = np.stack([1.0 + n[:, 2], -n[:, 1], n[:, 0], np.zeros(len(n))], 1)
    norm = np.linalg.norm(q, axis=1)
    anti = norm < 1e-6
    q[anti] = [0.0, 1.0, 0.0, 0.0]
    norm[anti] = 1.0
    return q / norm[:, None]


def disk_log_scales(points: np.ndarray, k: int = 3, flattening: float = DISK_FLATTENING) -> np.ndarray:
    """Log-scales [N, 3]: tangent axes = mean distance to the k nearest samples, normal axis flattened.

    Coincident samples would give log(0); distances are floored at 1e-4 of the median spacing.
    """
    pts = np.asarray(points, np.float64)
    k_eff = min(k, len(pts) - 1)
    if k_eff < 1:
        d = np.ones(len(pts))
    else:
        dist, _ = cKDTree(pts).query(pts, k=k_eff + 1, workers=-1)
        d = dist[:, 1:].mean(1)
        floor = 1e-4 * max(float(np.median(d)), 1e-12)
        d = np.maximum(d, floor)
    s = np.log(d)
    return np.stack([s, s, s + np.log(flattening)], 1)


def knn_indices(points: np.ndarray, k: int) -> np.ndarray:
    """Indices [N, k] of each point's k nearest other points (itself excluded); k is clipped to N - 1."""
    pts = np.asarray(points, np.float64)
    k_eff = min(k, len(pts) - 1)
    if k_eff < 1:
        return np.zeros((len(pts), 0), np.int64)
    _, idx = cKDTree(pts).query(pts, k=k_eff + 1, workers=-1)
    return np.asarray(idx[:, 1:], np.int64)


def surface_neighbours(points: np.ndarray, normals: np.ndarray, k: int) -> np.ndarray:
    """Indices [N, k] of each point's k nearest other points, -1 in place of those on the other side of the surface.

    Same side: unit `normals` [N, 3] with a positive dot product. Across a wall thinner than the sample
    spacing (a spatula's blade, a clamp's jaw) some of the nearest points in space are the far face's, whose
    colour, highlights and outward moves are not this face's: they are dropped, not replaced by farther
    same-side points, so a smoothness over these neighbours reaches as far along the surface as before.
    """
    idx = knn_indices(points, k)
    nrm = np.asarray(normals, np.float64)
    same = np.einsum("nd,nkd->nk", nrm, nrm[idx]) > 0.0
    return np.where(same, idx, -1)


def point_visibility(
    points: np.ndarray,
    normals: np.ndarray,
    viewmats: np.ndarray,
    Ks: np.ndarray,
    width: int,
    height: int,
    masks: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Which views see which points: visible [V, N] bool and the pixel each lands in, flat [V, N] int.

    points/normals [N, 3], viewmats [V, 4, 4], Ks [V, 3, 3], masks [V, H, W] bool. A view sees a
    point when the point faces it, projects inside the image (and its mask) and is not behind a
    nearer point (a z-buffer of the points themselves, one pixel each, with a depth tolerance of 1%
    of the object's extent).
    """
    pts = np.asarray(points, np.float64)
    nrm = np.asarray(normals, np.float64)
    v, n = len(viewmats), len(pts)
    visible = np.zeros((v, n), bool)
    flat_px = np.zeros((v, n), np.int64)
    tol = 0.01 * float(np.ptp(pts, axis=0).max() if n else 1.0)
    for i in range(v):
        uv, z = project_points(pts, Ks[i], viewmats[i], near=1e-9)
        ok = z > 1e-9
        px = np.floor(np.nan_to_num(uv, nan=-1.0)).astype(np.int64)
        ok &= (px[:, 0] >= 0) & (px[:, 0] < width) & (px[:, 1] >= 0) & (px[:, 1] < height)
        # Facing the camera: normal against the viewing ray (camera centre minus point).
        centre = -viewmats[i, :3, :3].T @ viewmats[i, :3, 3]
        ok &= np.einsum("nd,nd->n", nrm, centre - pts) > 0
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            continue
        flat = px[idx, 1] * width + px[idx, 0]
        zbuf = np.full(height * width, np.inf)
        np.minimum.at(zbuf, flat, z[idx])
        vis = z[idx] <= zbuf[flat] + tol
        if masks is not None:
            vis &= masks[i].reshape(-1)[flat]
        visible[i, idx[vis]] = True
        flat_px[i, idx[vis]] = flat[vis]
    return visible, flat_px


def project_colors(
    means: np.ndarray,
    normals: np.ndarray,
    images: np.ndarray,
    masks: np.ndarray | None,
    viewmats: np.ndarray,
    Ks: np.ndarray,
    *,
    default: float = 0.5,
) -> np.ndarray:
    """Mean colour [N, 3] of each point over the views that see it (`point_visibility`); `default`
    grey where none does. images [V, H, W, 3], masks [V, H, W] bool, viewmats [V, 4, 4], Ks [V, 3, 3]."""
    v, h, w = images.shape[:3]
    visible, flat_px = point_visibility(means, normals, viewmats, Ks, w, h, masks)
    acc = np.zeros((len(means), 3))
    cnt = np.zeros(len(means))
    for i in range(v):
        idx = np.flatnonzero(visible[i])
        vals = images[i].reshape(-1, 3)[flat_px[i, idx]]
        good = np.all(np.isfinite(vals), 1)  # a corrupt pixel must not poison a splat's colour
        acc[idx[good]] += vals[good]
        cnt[idx[good]] += 1
    out = np.full((len(means), 3), default)
    seen = cnt > 0
    out[seen] = acc[seen] / cnt[seen, None]
    return out


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """Colour in [0, 1] -> degree-0 SH coefficient (3DGS convention)."""
    return (np.asarray(rgb) - 0.5) / SH_C0


def init_splats(
    vertices: np.ndarray,
    faces: np.ndarray,
    n: int,
    *,
    sh_degree: int,
    face_part: np.ndarray | None = None,
    rgb: np.ndarray | None = None,
    opacity: float = 0.5,
    seed: int = 0,
) -> CanonicalSplats:
    """Splats on the mesh surface: area-uniform means, face normals, shortest-arc quats, disk scales,
    `opacity` (the paper's 0.5 by default), SH DC from `rgb` [N, 3] when given (see `project_colors`) else neutral grey
    0.5 (DC 0), higher SH bands 0. `face_part` [F] labels each face with its CAD part (default all 0).
    """
    if not 0.0 < opacity < 1.0:
        raise ValueError(f"initial opacity must lie strictly between 0 and 1, got {opacity}")
    rng = np.random.default_rng(seed)
    means, face_index, bary = sample_surface(vertices, faces, n, rng)
    _, face_normals = face_areas_normals(vertices, faces)
    normals = face_normals[face_index]
    k = (sh_degree + 1) ** 2
    sh = np.zeros((n, k, 3), np.float32)
    if rgb is not None:
        sh[:, 0] = rgb_to_sh_dc(rgb)
    part = np.zeros(len(faces), np.int64) if face_part is None else np.asarray(face_part, np.int64)
    gaussians = Gaussians(
        means=means.astype(np.float32),
        quats=normals_to_quats(normals).astype(np.float32),
        log_scales=disk_log_scales(means).astype(np.float32),
        opacity_logits=np.full(n, np.log(opacity / (1.0 - opacity)), np.float32),
        sh=sh,
    )
    return CanonicalSplats(
        gaussians=gaussians,
        normals=normals.astype(np.float32),
        face_index=face_index.astype(np.int64),
        barycentrics=bary.astype(np.float32),
        part_label=part[face_index],
    )


def alpha_half_reach(gaussians: Gaussians) -> np.ndarray:
    """How far [N] beyond its centre, in its own plane, each splat's alpha stays >= 1/2.

    alpha(d) = opacity * exp(-d^2 / (2 sigma^2)) crosses 1/2 at d = sigma * sqrt(2 ln(2 opacity)), with
    sigma the geometric mean of the two in-plane scales; a splat below opacity 1/2 never reaches it (0).
    """
    scales = np.sort(np.exp(np.asarray(gaussians.log_scales, np.float64)), axis=1)
    opacity = 1.0 / (1.0 + np.exp(-np.asarray(gaussians.opacity_logits, np.float64).reshape(-1)))
    sigma = np.sqrt(scales[:, 1] * scales[:, 2])
    return sigma * np.sqrt(2.0 * np.log(np.maximum(2.0 * opacity, 1.0)))

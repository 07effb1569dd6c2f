"""Inspection's silhouette refinement: the deviation map corrected where the capture's masks, at their own
resolution, place the part's outline more finely than the twin's surface does.

Where a view looks across the surface (its rim in that view), a move of the surface along its normal moves the
outline in the image by the move over the pixel's size there. At every rim vertex of every view the outline of the
twin's deformed surface is compared with the mask's, both as signed distance fields sampled at the vertex's image
(bilinear, so the offset is measured to a fraction of a pixel, and the two fields binarise the same way, so their
pixel-edge bias cancels). The offsets, converted to a move along each vertex's normal, are spread over the mesh
by a smoothing solve whose edges are weighted by how much two neighbours' normals agree (an outline's move says
nothing about a face seen square-on across a sharp edge), and added to the map where they are measured or
reach. The masks are taken at the camera's own resolution: the twin's cameras are rescaled to them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calibration.camera import Camera, project_points

RIM_COS = 0.3  # a view sees the vertex's rim when its line of sight is within ~17 deg of the tangent plane
RIM_BAND_PX = 1.0  # ... and the vertex's image lies this close to the surface's own rendered outline
SMOOTHING = 4.0  # neighbour coupling against one measurement's pull: spreads a rim offset over a few edges
PULL = 0.05  # every vertex's pull towards no correction: a rim's offset fades over about sqrt(SMOOTHING / PULL) edges


def signed_distance(mask: np.ndarray) -> np.ndarray:
    """[H, W] float: each pixel centre's distance in pixels to the mask's outline, the edge between its pixels (+ outside,
    - inside; mask [H, W] bool): +-0.5 beside the outline, so the field keeps its unit slope across it."""
    from scipy.ndimage import distance_transform_edt

    m = np.asarray(mask, bool)
    return np.where(m, 0.5 - distance_transform_edt(m), distance_transform_edt(~m) - 0.5)


def bilinear(field: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """`field` [H, W] at pixel coordinates uv [N, 2] (pixel centres at +0.5), clamped to the border."""
    h, w = field.shape
    x = np.clip(uv[:, 0] - 0.5, 0.0, w - 1.0)
    y = np.clip(uv[:, 1] - 0.5, 0.0, h - 1.0)
    x0, y0 = (
        np.minimum(np.floor(x).astype(np.int64), w - 2 if w > 1 else 0),
        np.minimum(np.floor(y).astype(np.int64), h - 2 if h > 1 else 0),
    )
    fx, fy = x - x0, y - y0
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    return field[y0, x0] * (1 - fx) * (1 - fy) + field[y0, x1] * fx * (1 - fy) + field[y1, x0] * (1 - fx) * fy + field[y1, x1] * fx * fy


def rim_offsets(
    vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, camera: Camera, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(vertex indices [M], signed move along the normal [M], units of the vertices) that would bring the rendered
    outline of the mesh (`vertices` [V, 3], `faces` [F, 3], unit `normals` [V, 3]) onto the `mask` [H, W] bool at its
    rim vertices in `camera` (rescaled to the mask's size). Positive: the surface should move out."""
    from reconstruction.mesh_raster import rasterize_mesh

    h, w = mask.shape
    cam = camera if (camera.width, camera.height) == (w, h) else camera.scaled(w, h)
    _, face_id, _ = rasterize_mesh(vertices, faces, cam)
    uv, z = project_points(vertices, cam.K, cam.viewmat, near=1e-6)
    to_cam = cam.center - vertices
    dist = np.maximum(np.linalg.norm(to_cam, axis=1), 1e-300)
    cos = np.einsum("ij,ij->i", normals, to_cam) / dist
    inside = np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] <= w) & (uv[:, 1] >= 0) & (uv[:, 1] <= h)
    sdf_model = signed_distance(face_id >= 0)
    near_outline = np.zeros(len(vertices), bool)
    near_outline[inside] = np.abs(bilinear(sdf_model, uv[inside])) <= RIM_BAND_PX
    rim = np.flatnonzero(inside & near_outline & (np.abs(cos) < RIM_COS))
    if rim.size == 0:
        return rim, np.zeros(0)
    uvr = uv[rim]
    # The outline moves out by s pixels where the mask's field is s lower than the model's at the vertex's image.
    s = bilinear(sdf_model, uvr) - bilinear(signed_distance(mask), uvr)
    footprint = z[rim] / (0.5 * (cam.K[0, 0] + cam.K[1, 1]))
    sin = np.sqrt(np.clip(1.0 - cos[rim] ** 2, 0.0, 1.0))
    return rim, s * footprint / np.maximum(sin, 1e-6)


def spread_on_mesh(
    num_vertices: int,
    faces: np.ndarray,
    normals: np.ndarray,
    index: np.ndarray,
    value: np.ndarray,
    smoothing: float = SMOOTHING,
    pull: float = PULL,
) -> np.ndarray:
    """field [V]: measurements `value` [M] at vertices `index` [M] (faces [F, 3], unit normals [V, 3]) spread over the mesh by
    min sum (x_i - value)^2 + smoothing sum_edges w_ab (x_a - x_b)^2 + pull sum_v x_v^2, w_ab = max(n_a . n_b, 0)^2:
    the measured offsets where they are, fading to no correction a few edges away."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    f = np.asarray(faces, np.int64)
    edges = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1), axis=0)
    a, b = edges[:, 0], edges[:, 1]
    w = smoothing * np.maximum(np.einsum("ij,ij->i", normals[a], normals[b]), 0.0) ** 2
    lap = sp.coo_matrix(
        (np.concatenate([w, w, -w, -w]), (np.concatenate([a, b, a, b]), np.concatenate([a, b, b, a]))), shape=(num_vertices, num_vertices)
    )
    counts = np.bincount(index, minlength=num_vertices).astype(np.float64)
    sums = np.bincount(index, weights=value, minlength=num_vertices)
    return np.asarray(spsolve((lap + sp.diags(counts + pull)).tocsc(), sums))


def silhouette_correction(
    vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, cameras: Sequence[Camera], masks: Sequence[np.ndarray]
) -> tuple[np.ndarray, np.ndarray, int]:
    """(correction [V] along the normals, units of the vertices (0 far from every rim); rim residual [V], the RMS of the measured offsets left after the correction at each measured vertex, NaN elsewhere;
    number of rim measurements) of the mesh (`vertices` [V, 3] as photographed, `faces` [F, 3], unit `normals`
    [V, 3]) against `masks` (one [H, W] bool per camera, any resolution)."""
    idx, val = [], []
    for cam, mask in zip(cameras, masks):
        i, v = rim_offsets(vertices, faces, normals, cam, np.asarray(mask, bool))
        idx.append(i)
        val.append(v)
    index = np.concatenate(idx) if idx else np.zeros(0, np.int64)
    value = np.concatenate(val) if val else np.zeros(0)
    n = len(vertices)
    if index.size == 0:
        return np.zeros(n), np.full(n, np.nan), 0
    field = spread_on_mesh(n, faces, normals, index, value)
    left = value - field[index]
    counts = np.bincount(index, minlength=n)
    rms = np.sqrt(np.bincount(index, weights=left**2, minlength=n) / np.maximum(counts, 1))
    return field, np.where(counts > 0, rms, np.nan), int(index.size)

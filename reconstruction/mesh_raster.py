"""A triangle mesh's z-buffer from a pinhole camera: which face each pixel centre sees, how deep, and where on it.

Inspection's visibility and heat maps and the silhouette refinement read meshes through this one rasterizer.
"""

from __future__ import annotations

import numba
import numpy as np

from calibration.camera import Camera, project_points

_NEAR = 1e-6


@numba.njit(cache=True, nogil=True)
def _zbuffer(uv, z, faces, depth, face_id, bary):
    """Nearest face per pixel centre: perspective-correct depth, face index and barycentrics."""
    h, w = depth.shape
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        if z[a] <= 1e-6 or z[b] <= 1e-6 or z[c] <= 1e-6:
            continue
        x0, y0, x1, y1, x2, y2 = uv[a, 0], uv[a, 1], uv[b, 0], uv[b, 1], uv[c, 0], uv[c, 1]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if area == 0.0:
            continue
        umin = max(int(np.ceil(min(x0, x1, x2) - 0.5)), 0)
        umax = min(int(np.floor(max(x0, x1, x2) - 0.5)), w - 1)
        vmin = max(int(np.ceil(min(y0, y1, y2) - 0.5)), 0)
        vmax = min(int(np.floor(max(y0, y1, y2) - 0.5)), h - 1)
        for v in range(vmin, vmax + 1):
            py = v + 0.5
            for u in range(umin, umax + 1):
                px = u + 0.5
                l0 = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) / area
                l1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) / area
                l2 = 1.0 - l0 - l1
                if l0 < 0.0 or l1 < 0.0 or l2 < 0.0:
                    continue
                w0, w1, w2 = l0 / z[a], l1 / z[b], l2 / z[c]
                s = w0 + w1 + w2
                d = 1.0 / s
                if d < depth[v, u]:
                    depth[v, u] = d
                    face_id[v, u] = f
                    bary[v, u, 0] = w0 * d
                    bary[v, u, 1] = w1 * d
                    bary[v, u, 2] = w2 * d


def rasterize_mesh(vertices: np.ndarray, faces: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Z-buffer of a triangle mesh seen by a pinhole `camera` (pixel centres at +0.5).

    Returns depth [H, W] (camera z, inf where empty), face index [H, W] (-1 where empty) and
    perspective-correct barycentrics [H, W, 3].
    """
    uv, z = project_points(vertices, camera.K, camera.viewmat, near=_NEAR)
    depth = np.full((camera.height, camera.width), np.inf)
    face_id = np.full((camera.height, camera.width), -1, np.int64)
    bary = np.zeros((camera.height, camera.width, 3))
    _zbuffer(uv, z, np.ascontiguousarray(faces, np.int64), depth, face_id, bary)
    return depth, face_id, bary

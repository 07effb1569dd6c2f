"""Mesh silhouettes for a pinhole camera, and their normalisation (paper section 3.2).

A silhouette needs no depth test: a pixel is inside when its centre lies inside any projected
triangle, so the renderer is a coverage fill of 2D triangles (numba, one pass over the faces).
Pixel (u, v) covers [u, u+1) x [v, v+1) and is tested at its centre (u + 0.5, v + 0.5), the same
convention as `calibration.camera.project_points`.

Normalisation makes silhouettes comparable regardless of where the object sits in the image and
how large it is: rotate to the principal axis of the mask (so in-plane roll is recovered in closed
form instead of sampled), crop to the tight bounding box, resize into an S x S canvas preserving
the aspect ratio (centred), and bit-pack.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from calibration.camera import project_points

# Triangles with a vertex closer than this (camera z, in the mesh's units) are dropped: a
# silhouette camera always sits outside the object, so only degenerate poses reach it.
_NEAR = 1e-6


def closed_winding(vertices: np.ndarray, faces: np.ndarray) -> int:
    """+1 or -1 when the faces [F, 3] close a surface wound outwards or inwards (of vertices [N, 3]), else 0.

    Closed: every directed edge has its reverse as often, so the surface has no boundary. A ray from a
    camera, outside it or inside, that meets it leaves it through a face turned away from the camera, so
    those faces alone fill its silhouette (`fill_triangles`' `winding`).
    """
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    if len(f) == 0:
        return 0
    n = int(f.max()) + 1
    tail, head = f.reshape(-1), np.roll(f, -1, axis=1).reshape(-1)
    if not np.array_equal(np.sort(tail * n + head), np.sort(head * n + tail)):
        return 0
    v = np.asarray(vertices, np.float64)
    volume = float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum())
    return int(np.sign(volume))


@numba.njit(cache=True, nogil=True)
def fill_triangles(uv: np.ndarray, faces: np.ndarray, ok: np.ndarray, out: np.ndarray, winding: int = 0) -> None:
    """Set `out` [H, W] where a pixel centre lies inside a projected triangle: `uv` [N, 2], `faces` [F, 3], `ok` [N] (vertex in front).

    `winding` ±1 (`closed_winding` of a closed surface) fills only the faces turned away from the camera, half the
    work for the same silhouette wherever the surface lies wholly in front of the camera; 0 fills every face.
    """
    h, w = out.shape
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        if not (ok[a] and ok[b] and ok[c]):
            continue
        x0, y0 = uv[a, 0], uv[a, 1]
        x1, y1 = uv[b, 0], uv[b, 1]
        x2, y2 = uv[c, 0], uv[c, 1]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        # With the image's y down, a face of an outward-wound surface turned away from the camera has area > 0.
        if area == 0.0 or area * winding < 0.0:
            continue
        sgn = 1.0 if area > 0 else -1.0
        # Pixel index range whose centres (i + 0.5) can fall inside the triangle's bbox.
        umin = max(int(np.ceil(min(x0, x1, x2) - 0.5)), 0)
        umax = min(int(np.floor(max(x0, x1, x2) - 0.5)), w - 1)
        vmin = max(int(np.ceil(min(y0, y1, y2) - 0.5)), 0)
        vmax = min(int(np.floor(max(y0, y1, y2) - 0.5)), h - 1)
        for v in range(vmin, vmax + 1):
            py = v + 0.5
            for u in range(umin, umax + 1):
                px = u + 0.5
                # Edge functions, inclusive: pixels on a shared edge are covered by both triangles. Or-ed in without
                # a branch: a registration's triangles span a few pixels each, whose outcomes no predictor guesses.
                e0 = sgn * ((x1 - x0) * (py - y0) - (y1 - y0) * (px - x0))
                e1 = sgn * ((x2 - x1) * (py - y1) - (y2 - y1) * (px - x1))
                e2 = sgn * ((x0 - x2) * (py - y2) - (y0 - y2) * (px - x2))
                out[v, u] |= (e0 >= 0.0) & (e1 >= 0.0) & (e2 >= 0.0)


def render_silhouette(
    vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, viewmat: np.ndarray, width: int, height: int, *, winding: int = 0
) -> np.ndarray:
    """Silhouette bool [height, width] of the mesh (`vertices` [N, 3], `faces` [F, 3]) seen by a pinhole camera.

    `K` [3, 3] (pixel centres at +0.5), `viewmat` [4, 4] world-to-camera (OpenCV axes). Distortion
    is not modelled: masks downstream are undistorted once at load. `winding`: the mesh's `closed_winding`,
    when known, to fill from half the faces.
    """
    uv, z = project_points(vertices, np.asarray(K, np.float64), np.asarray(viewmat, np.float64), near=_NEAR)
    out = np.zeros((int(height), int(width)), dtype=np.bool_)
    fill_triangles(uv, np.ascontiguousarray(faces, dtype=np.int64), z > _NEAR, out, winding)
    return out


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two bool masks of equal shape; 0 when both are empty."""
    union = np.count_nonzero(a | b)
    return float(np.count_nonzero(a & b) / union) if union else 0.0


@dataclass(frozen=True)
class Normalized:
    """A silhouette in canonical form.

    canvas: bool [S, S], principal axis horizontal, bbox-cropped, aspect-preserving resize, centred.
    angle: the image angle (radians, atan2 in (x right, y down) pixel axes) of the principal axis
        in the source mask; rotating the source by -angle about `centroid` gives the canonical form.
    centroid: [2] pixel coordinates (centres at +0.5) of the mask's centroid.
    extent: the larger side (pixels) of the canonical bounding box, the scale of the canvas.
    offset: [2] canonical bbox centre minus centroid, in the canonical (rotated) frame, pixels.
    anisotropy: 1 - minor/major second-moment eigenvalue ratio (0 = isotropic: angle is arbitrary).
    """

    canvas: np.ndarray
    angle: float
    centroid: np.ndarray
    extent: float
    offset: np.ndarray
    anisotropy: float

    @property
    def bbox_center(self) -> np.ndarray:
        """Centre [2] of the canonical bounding box in source pixel coordinates: the point the canvas is centred on."""
        c, s = np.cos(self.angle), np.sin(self.angle)
        return self.centroid + np.array([[c, -s], [s, c]]) @ self.offset


def principal_axis(mask: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Centroid [2] (pixel centres at +0.5), principal-axis angle (radians) and anisotropy of a bool mask [H, W]."""
    m = cv2.moments(mask.astype(np.uint8), binaryImage=True)
    if m["m00"] <= 0:
        raise ValueError("the mask is empty")
    cx, cy = m["m10"] / m["m00"] + 0.5, m["m01"] / m["m00"] + 0.5
    mu20, mu02, mu11 = m["mu20"] / m["m00"], m["mu02"] / m["m00"], m["mu11"] / m["m00"]
    angle = 0.5 * np.arctan2(2.0 * mu11, mu20 - mu02)
    root = np.sqrt(max((mu20 - mu02) ** 2 + 4.0 * mu11**2, 0.0))
    lam1, lam2 = 0.5 * (mu20 + mu02 + root), 0.5 * (mu20 + mu02 - root)
    aniso = 1.0 - lam2 / lam1 if lam1 > 0 else 0.0
    return np.array([cx, cy]), float(angle), float(aniso)


def normalize_silhouette(mask: np.ndarray, size: int, *, angle: float | None = None) -> Normalized:
    """Canonical form of a bool mask [H, W] in an S x S canvas (S = `size`).

    `angle` overrides the principal-axis angle (used to try the other rolls of a near-isotropic
    or 180-degree-ambiguous mask).
    """
    centroid, axis, aniso = principal_axis(mask)
    angle = axis if angle is None else float(angle)
    # Rotate about the centroid by -angle into a canvas big enough for any rotation of the mask.
    ys, xs = np.nonzero(mask)
    r = float(np.sqrt(((xs + 0.5 - centroid[0]) ** 2 + (ys + 0.5 - centroid[1]) ** 2).max())) + 2.0
    side = int(np.ceil(2 * r))
    c, s = np.cos(angle), np.sin(angle)
    # Canonical coords q = R(-angle) (p - centroid) + side/2; cv2 uses integer pixel centres.
    rot = np.array([[c, s], [-s, c]])
    shift = side / 2.0 - rot @ centroid
    affine = np.hstack([rot, shift[:, None]])
    affine[:, 2] += affine[:, :2] @ np.array([0.5, 0.5]) - 0.5
    canon = cv2.warpAffine(mask.astype(np.uint8) * 255, affine, (side, side), flags=cv2.INTER_LINEAR) > 127
    if not canon.any():
        canon = cv2.warpAffine(mask.astype(np.uint8) * 255, affine, (side, side), flags=cv2.INTER_NEAREST) > 127
    rows = np.flatnonzero(canon.any(1))
    cols = np.flatnonzero(canon.any(0))
    y0, y1, x0, x1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    crop = canon[y0:y1, x0:x1]
    extent = float(max(y1 - y0, x1 - x0))
    offset = np.array([(x0 + x1) / 2.0 - side / 2.0, (y0 + y1) / 2.0 - side / 2.0])
    return Normalized(fit_canvas(crop, size), angle, centroid, extent, offset, aniso)


def fit_canvas(crop: np.ndarray, size: int) -> np.ndarray:
    """Aspect-preserving resize of a bool crop [h, w] into a centred bool [size, size] canvas (area-averaged, threshold 0.5)."""
    h, w = crop.shape
    scale = size / max(h, w)
    nh, nw = max(1, int(round(h * scale))), max(1, int(round(w * scale)))
    small = cv2.resize(crop.astype(np.float32), (nw, nh), interpolation=cv2.INTER_AREA) >= 0.5
    out = np.zeros((size, size), dtype=np.bool_)
    oy, ox = (size - nh) // 2, (size - nw) // 2
    out[oy : oy + nh, ox : ox + nw] = small
    return out


def pack(canvases: np.ndarray) -> np.ndarray:
    """Bool canvases [..., S, S] -> packed uint64 words [..., ceil(S*S/64)] (zero-padded)."""
    flat = canvases.reshape(canvases.shape[:-2] + (-1,))
    bits = flat.shape[-1]
    words = -(-bits // 64)
    padded = np.zeros(flat.shape[:-1] + (words * 64,), dtype=np.bool_)
    padded[..., :bits] = flat
    return np.packbits(padded, axis=-1).view(np.uint64)


def unpack(words: np.ndarray, size: int) -> np.ndarray:
    """Inverse of `pack`: [..., W] uint64 -> bool [..., size, size]."""
    bits = np.unpackbits(np.ascontiguousarray(words).view(np.uint8), axis=-1)[..., : size * size]
    return bits.reshape(words.shape[:-1] + (size, size)).astype(bool)

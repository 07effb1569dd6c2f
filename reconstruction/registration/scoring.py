"""Silhouette scores of a mesh under a rig-to-object Sim(3) in every view: the numba kernels and `Scorer`.

Score: per view, half IoU and half an edge term exp(-chamfer / tau) on the silhouette boundaries.
IoU alone collapses for thin parts (rings, wire forms, forks) a few pixels off; the contour distance
keeps a slope the search can follow.
"""

from __future__ import annotations

import cv2
import numba
import numpy as np

from calibration.camera import Camera
from calibration.sim3 import Sim3
from reconstruction.library import Library
from reconstruction.parallel import parallel_for
from reconstruction.silhouette import closed_winding, fill_triangles

# Longest image side used when scoring hypotheses and when refining.
SCORE_PX = 128
REFINE_PX = 192
# Objective = (1 - EDGE_WEIGHT) IoU + EDGE_WEIGHT exp(-chamfer / tau): half area, half contour,
# so a thick part is still judged mostly by area while a thin one keeps a smooth score.
EDGE_WEIGHT = 0.5
# tau = EDGE_TAU x the observed silhouette's bbox diagonal (px), at least EDGE_TAU_MIN_PX: the
# edge term halves when the contours are ~2 % of the object's image size apart on average.
EDGE_TAU = 0.03
EDGE_TAU_MIN_PX = 1.0


@numba.njit(cache=True, nogil=True)
def _boundary_dt(sil: np.ndarray, dt: np.ndarray) -> int:
    """Two-pass chamfer (1, sqrt 2) distance [H, W] to the boundary pixels of `sil` (inside pixels
    with a 4-neighbour outside or on the image edge); returns the number of boundary pixels."""
    h, w = sil.shape
    big = np.float32(1e9)
    n = 0
    for r in range(h):
        for c in range(w):
            edge = False
            if sil[r, c]:
                edge = (
                    r == 0
                    or c == 0
                    or r == h - 1
                    or c == w - 1
                    or not sil[r - 1, c]
                    or not sil[r + 1, c]
                    or not sil[r, c - 1]
                    or not sil[r, c + 1]
                )
            if edge:
                dt[r, c] = 0.0
                n += 1
            else:
                dt[r, c] = big
    d1, d2 = np.float32(1.0), np.float32(1.4142135)
    # Each pass takes a row's three neighbours in the row before it first (independent along the row), then its
    # neighbour in the same row: that chain, one add and one min a pixel, is the pass's latency. min is exact in
    # any order, so the distances are those of the one-loop form.
    for r in range(h):
        if r > 0:
            for c in range(w):
                v = min(dt[r, c], dt[r - 1, c] + d1)
                if c > 0:
                    v = min(v, dt[r - 1, c - 1] + d2)
                if c < w - 1:
                    v = min(v, dt[r - 1, c + 1] + d2)
                dt[r, c] = v
        for c in range(1, w):
            dt[r, c] = min(dt[r, c], dt[r, c - 1] + d1)
    for r in range(h - 1, -1, -1):
        if r < h - 1:
            for c in range(w):
                v = min(dt[r, c], dt[r + 1, c] + d1)
                if c < w - 1:
                    v = min(v, dt[r + 1, c + 1] + d2)
                if c > 0:
                    v = min(v, dt[r + 1, c - 1] + d2)
                dt[r, c] = v
        for c in range(w - 2, -1, -1):
            dt[r, c] = min(dt[r, c], dt[r, c + 1] + d1)
    return n


@numba.njit(cache=True, nogil=True)
def _view_scores(
    lo: int,
    hi: int,
    verts: np.ndarray,
    faces: np.ndarray,
    winding: int,
    ks: np.ndarray,
    viewmats: np.ndarray,
    masks: np.ndarray,
    obs_dt: np.ndarray,
    obs_edges: np.ndarray,
    n_edges: np.ndarray,
    obs_boxes: np.ndarray,
    sizes: np.ndarray,
    counts: np.ndarray,
    taus: np.ndarray,
    edge_weight: float,
    stop_below: float,
    iou: np.ndarray,
    obj: np.ndarray,
) -> None:
    """Views lo..hi-1: writes IoU iou [V] and the objective obj [V] = (1 - edge_weight) IoU + edge_weight exp(-chamfer / tau).

    chamfer: symmetric mean distance (px) between the rendered and the observed silhouette
    boundaries (`obs_dt` [V, H, W] distance to the observed boundary; `obs_edges` [V, E, 2] its
    pixels, `n_edges` [V] of them valid). Work is confined to the union of the projected mesh's
    bbox and the observed mask's bbox `obs_boxes` [V, 4] (r0, r1, c0, c1, exclusive ends). Stops
    early (remaining views left as they were) once the objective sum over lo..hi-1 cannot reach `stop_below`.
    The mesh `verts` [N, 3] (rig frame), `faces` [F, 3] is drawn from the faces `winding` selects (`fill_triangles`).
    """
    n_views = hi - lo
    total = 0.0
    hmax, wmax = masks.shape[1], masks.shape[2]
    buf = np.zeros((hmax, wmax), dtype=np.bool_)
    dt = np.zeros((hmax, wmax), dtype=np.float32)
    uv = np.empty((verts.shape[0], 2))
    ok = np.empty(verts.shape[0], dtype=np.bool_)
    for v in range(lo, hi):
        h, w = sizes[v, 0], sizes[v, 1]
        vm = viewmats[v]
        k = ks[v]
        umin, umax, vmin, vmax = 1e30, -1e30, 1e30, -1e30
        for i in range(verts.shape[0]):
            x = vm[0, 0] * verts[i, 0] + vm[0, 1] * verts[i, 1] + vm[0, 2] * verts[i, 2] + vm[0, 3]
            y = vm[1, 0] * verts[i, 0] + vm[1, 1] * verts[i, 1] + vm[1, 2] * verts[i, 2] + vm[1, 3]
            z = vm[2, 0] * verts[i, 0] + vm[2, 1] * verts[i, 1] + vm[2, 2] * verts[i, 2] + vm[2, 3]
            ok[i] = z > 1e-9
            zz = z if ok[i] else 1.0
            uv[i, 0] = k[0, 0] * x / zz + k[0, 1] * y / zz + k[0, 2]
            uv[i, 1] = k[1, 1] * y / zz + k[1, 2]
            if ok[i]:
                umin, umax = min(umin, uv[i, 0]), max(umax, uv[i, 0])
                vmin, vmax = min(vmin, uv[i, 1]), max(vmax, uv[i, 1])
        # The region where anything can be rendered or observed (one pixel of margin).
        r0 = max(0, min(obs_boxes[v, 0], int(max(vmin, -1.0)) - 1))
        r1 = min(h, max(obs_boxes[v, 1], int(min(vmax, h + 1.0)) + 2))
        c0 = max(0, min(obs_boxes[v, 2], int(max(umin, -1.0)) - 1))
        c1 = min(w, max(obs_boxes[v, 3], int(min(umax, w + 1.0)) + 2))
        view = buf[:h, :w]
        fill_triangles(uv, faces, ok, view, winding)
        inter = 0
        rendered = 0
        for r in range(r0, r1):
            for c in range(c0, c1):
                if buf[r, c]:
                    rendered += 1
                    if masks[v, r, c]:
                        inter += 1
        union = rendered + counts[v] - inter
        iou[v] = inter / union if union > 0 else 0.0
        edge = 0.0
        if edge_weight > 0.0 and rendered > 0 and n_edges[v] > 0:
            sub = buf[r0:r1, c0:c1]
            dview = dt[r0:r1, c0:c1]
            n_r = _boundary_dt(sub, dview)
            # Rendered boundary -> observed boundary: the observed distance map at the rendered edge pixels.
            r2o = 0.0
            for r in range(r1 - r0):
                for c in range(c1 - c0):
                    if dview[r, c] == 0.0:
                        r2o += obs_dt[v, r + r0, c + c0]
            o2r = 0.0
            for e in range(n_edges[v]):
                o2r += dview[obs_edges[v, e, 0] - r0, obs_edges[v, e, 1] - c0]
            cham = 0.5 * (r2o / max(n_r, 1) + o2r / n_edges[v])
            edge = np.exp(-cham / taus[v])
        for r in range(r0, r1):
            for c in range(c0, c1):
                buf[r, c] = False
        obj[v] = (1.0 - edge_weight) * iou[v] + edge_weight * edge
        total += obj[v]
        if total + (n_views - 1 - (v - lo)) < stop_below:
            break


def boundary(mask: np.ndarray) -> np.ndarray:
    """Boundary pixels of a bool mask [H, W] (inside, with a 4-neighbour outside or on the image edge) -> bool [H, W]."""
    cross = cv2.erode(
        mask.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3)), borderType=cv2.BORDER_CONSTANT, borderValue=0
    )
    return mask & (cross == 0)


class Scorer:
    """Per-view silhouette scores of a mesh under a rig-to-object Sim(3), on masks downscaled to `max_px`.

    Two scores per view: the IoU, and the objective registration optimises, which blends the IoU with
    an edge term (the symmetric chamfer distance between rendered and observed silhouette boundaries,
    through exp(-d / tau)): IoU collapses for a thin part a few pixels off, the edge term degrades
    smoothly with the pose error, so the search still sees which way is better.
    """

    def __init__(self, masks: np.ndarray, cameras: list[Camera], max_px: int, *, edge_weight: float | None = None):
        small, ks, vms, sizes = [], [], [], []
        for m, cam in zip(masks, cameras):
            s = min(1.0, max_px / max(cam.width, cam.height))
            w, h = max(1, round(cam.width * s)), max(1, round(cam.height * s))
            c = cam.scaled(w, h)
            small.append(cv2.resize(cam.crop(m).astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) >= 0.5)
            ks.append(c.K)
            vms.append(c.viewmat)
            sizes.append((h, w))
        hm, wm = max(s[0] for s in sizes), max(s[1] for s in sizes)
        n = len(small)
        self.edge_weight = EDGE_WEIGHT if edge_weight is None else float(edge_weight)
        self.masks = np.zeros((n, hm, wm), dtype=np.bool_)
        self.obs_dt = np.zeros((n, hm, wm), dtype=np.float32)
        edges = []
        self.taus = np.zeros(n)
        # An empty mask's box is empty (r0 > r1), so only the rendering decides the region.
        self.obs_boxes = np.tile(np.array([hm, 0, wm, 0], np.int64), (n, 1))
        for i, m in enumerate(small):
            self.masks[i, : m.shape[0], : m.shape[1]] = m
            ys, xs = np.nonzero(m)
            if len(xs):
                self.obs_boxes[i] = (ys.min(), ys.max() + 1, xs.min(), xs.max() + 1)
            if self.edge_weight == 0.0:
                edges.append(np.zeros((0, 2), np.int64))
                continue
            b = boundary(m)
            # Distance (px) to the nearest observed boundary pixel, over the whole padded canvas.
            canvas = np.ones((hm, wm), np.uint8)
            canvas[: m.shape[0], : m.shape[1]][b] = 0
            self.obs_dt[i] = cv2.distanceTransform(canvas, cv2.DIST_L2, 5) if b.any() else 0.0
            edges.append(np.argwhere(b))
            diag = float(np.hypot(np.ptp(xs) + 1, np.ptp(ys) + 1)) if len(xs) else 0.0
            self.taus[i] = max(EDGE_TAU_MIN_PX, EDGE_TAU * diag)
        self.n_edges = np.array([len(e) for e in edges], dtype=np.int64)
        self.obs_edges = np.zeros((n, max(1, int(self.n_edges.max())), 2), dtype=np.int64)
        for i, e in enumerate(edges):
            self.obs_edges[i, : len(e)] = e
        self.ks = np.array(ks)
        self.viewmats = np.array(vms)
        self.sizes = np.array(sizes, dtype=np.int64)
        self.counts = self.masks.reshape(n, -1).sum(1).astype(np.int64)

    def scores(
        self,
        vertices_obj: np.ndarray,
        faces: np.ndarray,
        sim3_rig_to_object: Sim3,
        *,
        stop_below: float = -1.0,
        parallel: bool = True,
        winding: int = 0,
    ) -> tuple[np.ndarray, np.ndarray]:
        """IoU [V] and objective [V] of the mesh (object frame) seen by the rig cameras under the Sim(3).

        With `stop_below`, scoring stops once the objective sum cannot reach it (the rest stay 0).
        `parallel=False` keeps the work on the calling thread (for callers that score several poses at once).
        `winding`: the mesh's `closed_winding`, when known: a closed mesh's silhouettes are drawn from half its faces.
        """
        s, r, t = sim3_rig_to_object.scale, sim3_rig_to_object.rotation, sim3_rig_to_object.translation
        verts_rig = ((vertices_obj - t) @ r) / s
        n = len(self.ks)
        iou, obj = np.zeros(n), np.zeros(n)
        args = (
            verts_rig,
            faces,
            int(winding),
            self.ks,
            self.viewmats,
            self.masks,
            self.obs_dt,
            self.obs_edges,
            self.n_edges,
            self.obs_boxes,
            self.sizes,
            self.counts,
            self.taus,
            self.edge_weight,
        )
        if stop_below > -1.0 or not parallel:
            # Cutting short depends on the running sum over the views in order: one thread.
            _view_scores(0, n, *args, float(stop_below), iou, obj)
        else:
            # Views are independent: any split over the threads gives the same scores.
            parallel_for(_view_scores, n, *args, -1.0, iou, obj)
        return iou, obj

    def __call__(
        self, vertices_obj: np.ndarray, faces: np.ndarray, sim3_rig_to_object: Sim3, *, stop_below: float = -1.0, winding: int = 0
    ) -> np.ndarray:
        """IoU per view [V] of the mesh (object frame) seen by the rig cameras under the Sim(3)."""
        return self.scores(vertices_obj, faces, sim3_rig_to_object, stop_below=stop_below, winding=winding)[0]


def cut_short(obj: np.ndarray, stop_below: float) -> np.ndarray:
    """The objectives [V] that `_view_scores` leaves when it scores views in order and stops once their running
    sum cannot reach `stop_below` (views after the stop stay 0); `obj` must hold every view up to that stop."""
    out = np.zeros_like(obj)
    total = 0.0
    for v in range(len(obj)):
        out[v] = obj[v]
        total += obj[v]
        if total + (len(obj) - 1 - v) < stop_below:
            break
    return out


def scoring_shape(library: Library, model_id: str) -> tuple[np.ndarray, np.ndarray, int]:
    """The model's scoring mesh (vertices [N, 3], faces [F, 3]) and its `closed_winding`, for `Scorer.scores`."""
    verts, faces = library.scoring_mesh(model_id)
    return verts, faces, closed_winding(verts, faces)

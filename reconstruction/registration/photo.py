"""Image evidence for a near-tie: near-symmetric poses give nearly the same silhouettes, but a
textured part's colours line up across views only at the right one."""

from __future__ import annotations

import numpy as np

from calibration.camera import Camera
from calibration.sim3 import Sim3

# Photo-consistency z-buffer cell (px), and the ratio of colour disagreements below which the images
# overrule the silhouettes on a near-tie (evidence: benchmarks/results/registration_rig_scenes.md).
PHOTO_CELL_PX = 2
PHOTO_DECISIVE = 0.9


def photo_disagreement(images: np.ndarray, cameras_rig: list[Camera], verts: np.ndarray, faces: np.ndarray, sim3: Sim3) -> float:
    """How much the views disagree on the colour of the model's surface under a pose (lower = the
    images agree better): per surface point the median absolute deviation of its colour across the
    views that see it (at least three), summed over RGB, averaged over points. `images` [V, H, W, 3]
    float in [0, 1], views of mixed sizes top-left on one canvas.

    Points are face centroids; a view sees a point when the face faces it and the point is the
    nearest one within its PHOTO_CELL_PX cell of that view (a point z-buffer; the median keeps a
    point wrongly seen through a sparse front surface from counting). Near-symmetric poses give
    nearly the same silhouettes, but a textured part's colours line up across views only at the
    right one.
    """
    tri = verts[faces]
    pts = tri.mean(1)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inv = sim3.inverse()
    pts_rig = inv.apply(pts)
    n_rig = normals @ inv.rotation.T
    cols = np.full((len(cameras_rig), len(pts), 3), np.nan)
    for v, cam in enumerate(cameras_rig):
        uv, z = cam.project(pts_rig)
        facing = np.einsum("ij,ij->i", n_rig, pts_rig - cam.center) < 0
        h, w = cam.height, cam.width  # its own pixels of a canvas shared with larger views
        inside = facing & (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        idx = np.flatnonzero(inside)
        if len(idx) == 0:
            continue
        cell = (uv[idx] // PHOTO_CELL_PX).astype(np.int64)
        key = cell[:, 1] * (w // PHOTO_CELL_PX + 1) + cell[:, 0]
        order = np.lexsort((z[idx], key))
        first = np.ones(len(order), bool)
        first[1:] = key[order][1:] != key[order][:-1]
        seen = idx[order][first]
        cols[v, seen] = bilinear(images[v][:h, :w], uv[seen])
    count = np.sum(~np.isnan(cols[..., 0]), axis=0)
    multi = count >= 3
    if not multi.any():
        return float("nan")
    sub = cols[:, multi]
    return float(np.nanmedian(np.abs(sub - np.nanmedian(sub, axis=0)), axis=0).sum(-1).mean())


def bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Colours [N, 3] of `image` [H, W, 3+] at pixel coordinates `uv` [N, 2] (pixel centres at +0.5), bilinear, clamped at the border."""
    h, w = image.shape[:2]
    x = np.clip(uv[:, 0] - 0.5, 0, w - 1)
    y = np.clip(uv[:, 1] - 0.5, 0, h - 1)
    x0, y0 = np.minimum(x.astype(np.int64), w - 2 if w > 1 else 0), np.minimum(y.astype(np.int64), h - 2 if h > 1 else 0)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    img = image[..., :3]
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def break_tie(
    images: np.ndarray,
    cameras_rig: list[Camera],
    verts: np.ndarray,
    faces: np.ndarray,
    pose: Sim3,
    score: float,
    alt_pose: Sim3,
    alt_score: float,
    ambiguity: dict,
) -> tuple[Sim3, float]:
    """The winner of a near-tie between `pose` (the silhouettes' choice, objective `score`) and `alt_pose`: the alternative
    when its colours agree better across views by the PHOTO_DECISIVE ratio. Records both disagreements and what decided
    in `ambiguity` (its score_gap turns negative and its alternative becomes `pose` when the images overrule; both
    disagreements are None when no surface point is seen by three views)."""
    pd, pd_alt = (
        photo_disagreement(images, cameras_rig, verts, faces, pose),
        photo_disagreement(images, cameras_rig, verts, faces, alt_pose),
    )
    if np.isnan(pd) or np.isnan(pd_alt):
        # No surface point is seen by three views (two views, cameras facing away): the images cannot decide.
        ambiguity.update(photo_disagreement=None, alternative_photo_disagreement=None, decided_by="silhouettes")
        return pose, score
    decisive = bool(pd_alt < PHOTO_DECISIVE * pd)
    if decisive:
        ambiguity["alternative_sim3_rig_to_object"] = pose.to_dict()
        pose, score, alt_score, pd, pd_alt = alt_pose, alt_score, score, pd_alt, pd
        ambiguity["score_gap"], ambiguity["alternative_score"] = float(score - alt_score), float(alt_score)
    ambiguity.update(photo_disagreement=pd, alternative_photo_disagreement=pd_alt, decided_by="images" if decisive else "silhouettes")
    return pose, score

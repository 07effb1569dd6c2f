"""Pose hypotheses from single views, and Sim(3) candidates from pairs of them.

Each observed mask is rotated to a virtual camera looking at its centroid (a homography, so the
off-axis perspective is undone), normalised like the library silhouettes, and matched against the
whole index: its top-k library views with IoU >= threshold are camera-to-object pose hypotheses
(rotation from the grid direction plus the closed-form in-plane roll; distance from the silhouette's
size; position from the bbox centre through the intrinsics). Two hypotheses of one model in two views
give a rig-to-object Sim(3) (`sim3_from_pair`).

Masks touching the image border have a truncated bbox: they are flagged (`Observation.truncated`)
so the search seeds from them only when no other view can.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration.camera import Camera
from calibration.sim3 import Sim3
from calibration.so3 import rotation_between
from reconstruction.library import Library
from reconstruction.registration.result import SCALE_SEARCH
from reconstruction.silhouette import normalize_silhouette, pack
from reconstruction.silhouette_index import ANGLE, BX, BY, EXTENT, SilhouetteIndex

# Below this anisotropy the principal axis of a mask is unreliable; such masks are tried at many rolls.
ISOTROPIC = 0.25
ISOTROPIC_ROLLS = 24


@dataclass(frozen=True)
class Observation:
    """One observed mask in library form.

    r_virtual [3, 3]: p_cam = r_virtual @ p_virtual (the virtual camera looks at the mask centroid).
    variants [Q, W] packed canvases at the roll `angles` [Q]; `extents` [Q] and `bbox_centers` [Q, 2]
    in normalised virtual-camera units.
    """

    r_virtual: np.ndarray
    variants: np.ndarray
    angles: np.ndarray
    extents: np.ndarray
    bbox_centers: np.ndarray
    truncated: bool


@dataclass(frozen=True)
class Hypothesis:
    """A camera-to-object pose for one view from one library row."""

    view: int
    model: int
    iou: float
    r_obj_cam: np.ndarray
    center_obj: np.ndarray


def touches_border(mask: np.ndarray) -> bool:
    return bool(mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())


def observe(mask: np.ndarray, camera: Camera, canvas: int) -> Observation | None:
    """Library form of a bool mask [H, W] seen by a pinhole `camera`; None for an empty mask."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return None
    k = camera.K
    ray = np.linalg.solve(k, [xs.mean() + 0.5, ys.mean() + 0.5, 1.0])
    r_v = rotation_between(np.array([0.0, 0.0, 1.0]), ray)
    f_v = float(np.sqrt(k[0, 0] * k[1, 1]))
    # Homography original pixels -> virtual pixels, sized to hold the warped mask.
    pts = np.stack([xs + 0.5, ys + 0.5, np.ones(len(xs))], 1)[:: max(1, len(xs) // 4000)]
    proj = (r_v.T @ np.linalg.solve(k, pts.T)).T
    xy = proj[:, :2] / proj[:, 2:3] * f_v
    half = float(np.abs(xy).max()) * 1.1 + 4.0
    side = int(np.clip(2 * half, 16, 4096))
    scale = min(1.0, side / (2 * half))
    kv = np.array([[f_v * scale, 0, side / 2], [0, f_v * scale, side / 2], [0, 0, 1.0]])
    h = kv @ r_v.T @ np.linalg.inv(k)
    shift = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1.0]])
    h_cv = shift @ h @ np.linalg.inv(shift)
    warped = cv2.warpPerspective(mask.astype(np.uint8) * 255, h_cv, (side, side), flags=cv2.INTER_LINEAR) > 127
    if not warped.any():
        return None
    base = normalize_silhouette(warped, canvas)
    if base.anisotropy < ISOTROPIC:
        angles = base.angle + np.arange(ISOTROPIC_ROLLS) * (2 * np.pi / ISOTROPIC_ROLLS)
    else:
        angles = base.angle + np.array([0.0, np.pi])
    norms = [normalize_silhouette(warped, canvas, angle=a) for a in angles]
    fv = f_v * scale
    return Observation(
        r_virtual=r_v,
        variants=pack(np.stack([n.canvas for n in norms])),
        angles=np.array([n.angle for n in norms]),
        extents=np.array([n.extent / fv for n in norms]),
        bbox_centers=np.array([(n.bbox_center - side / 2) / fv for n in norms]),
        truncated=touches_border(mask),
    )


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def hypothesis(obs: Observation, view: int, index: SilhouetteIndex, row: int, variant: int, iou: float) -> Hypothesis:
    """Camera-to-object pose of view `view` if it sees library row `row` (matched at roll `variant`)."""
    geom = index.geom[row]
    model = int(index.model_row[row])
    r_lib = index.rotations[int(index.dir_idx[row])]
    center = index.centers[model]
    d_lib = index.grid.distance(float(index.radii[model]))
    alpha = float(obs.angles[variant] - geom[ANGLE])
    k = float(obs.extents[variant] / geom[EXTENT])
    rot2 = _rz(alpha)[:2, :2]
    # The model centre sits on the library camera's axis; carry it through the roll and zoom.
    c_img = obs.bbox_centers[variant] - k * rot2 @ np.array([geom[BX], geom[BY]], np.float64)
    p_virtual = (d_lib / k) * np.array([c_img[0], c_img[1], 1.0])
    r_obj_virtual = r_lib @ _rz(alpha).T
    return Hypothesis(view, model, iou, r_obj_virtual @ obs.r_virtual.T, center - r_obj_virtual @ p_virtual)


def sim3_from_pair(
    first: Hypothesis,
    second: Hypothesis | None,
    cameras: list[Camera],
    center: np.ndarray,
    *,
    band: tuple[float, float] = SCALE_SEARCH,
    expected_scale: float | None = None,
) -> list[Sim3]:
    """Rig-to-object Sim(3) candidates: rotation and translation from `first`, scale from `second`.

    The paper's scale is the ratio of inter-camera distances |C_i - C_j|_obj / |C_i - C_j|_rig; it
    needs the second hypothesis's rotation right too. The second candidate scale only asks the
    second camera's distance to the model `center` to match its hypothesis (it depends on the
    silhouette's size, not its rotation), which makes a good first hypothesis enough. Scales are
    clipped to `band`; `expected_scale` (a metric rig's) is always a candidate, and the only one
    without `second` (else 1).
    """
    ci = cameras[first.view]
    r = first.r_obj_cam @ ci.c2w[:3, :3].T
    scales = [1.0 if expected_scale is None else expected_scale]
    if second is not None:
        b = r @ (cameras[second.view].center - ci.center)
        b2 = float(b @ b)
        b_obj = np.linalg.norm(first.center_obj - second.center_obj)
        if b2 > 0 and b_obj > 0:
            scales = [float(b_obj / np.sqrt(b2))]
            # |C_i + s b - c|^2 = rho^2, a quadratic in s.
            a = first.center_obj - center
            rho2 = float(np.sum((second.center_obj - center) ** 2))
            bb, cc = 2.0 * float(a @ b), float(a @ a) - rho2
            disc = bb * bb - 4.0 * b2 * cc
            if disc >= 0:
                scales += [x for x in ((-bb + np.sqrt(disc)) / (2 * b2), (-bb - np.sqrt(disc)) / (2 * b2)) if x > 0]
            if expected_scale is not None:
                scales.append(expected_scale)
    kept: list[float] = []
    for x in scales:
        x = float(np.clip(x, *band))
        if all(abs(x / k - 1.0) > 1e-3 for k in kept):
            kept.append(x)
    return [Sim3(s, r, first.center_obj - s * r @ ci.center) for s in kept]


def match_views(
    observations: list[Observation | None], index: SilhouetteIndex, *, top_k: int, iou_threshold: float, model_mask: np.ndarray | None
) -> tuple[list[list[Hypothesis]], float]:
    """Top-k hypotheses per view and the best IoU seen anywhere."""
    hyps, best_seen = [], 0.0
    for v, obs in enumerate(observations):
        if obs is None:
            hyps.append([])
            continue
        m = index.query(obs.variants, top_k=top_k, min_iou=iou_threshold, model_mask=model_mask)
        best_seen = max(best_seen, m.best_iou)
        hyps.append([hypothesis(obs, v, index, int(r), int(q), float(i)) for r, q, i in zip(m.rows, m.variant, m.iou)])
    return hyps, best_seen


def independent_poses(
    masks: np.ndarray, cameras: list[Camera], library: Library, *, model_ids: list[str] | None = None
) -> list[tuple[str, np.ndarray] | None]:
    """Each view matched alone to its single best library silhouette (paper Fig. 5b, for contrast):
    per view (model id, camera-to-object c2w [4, 4]) or None."""
    index = library.index
    model_mask = None if model_ids is None else np.isin(np.array(index.model_ids), model_ids)
    out = []
    for v, (mask, cam) in enumerate(zip(masks, cameras)):
        obs = observe(mask, cam, index.grid.canvas)
        m = index.query(obs.variants, top_k=1, min_iou=0.0, model_mask=model_mask) if obs is not None else None
        if m is None or len(m.rows) == 0:
            out.append(None)
            continue
        h = hypothesis(obs, v, index, int(m.rows[0]), int(m.variant[0]), float(m.iou[0]))
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = h.r_obj_cam, h.center_obj
        out.append((index.model_ids[h.model], c2w))
    return out

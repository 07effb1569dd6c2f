"""Silhouette consensus registration of a calibrated rig to a CAD library (paper section 3.2).

1. Each observed mask is rotated to a virtual camera looking at its centroid (a homography, so
   the off-axis perspective is undone), normalised like the library silhouettes, and matched
   against the whole index: its top-k library views with IoU >= threshold are camera-to-object
   pose hypotheses (rotation from the grid direction plus the closed-form in-plane roll; distance
   from the silhouette's size; position from the bbox centre through the intrinsics).
2. RANSAC over Sim(3): sample two views and one hypothesis of the same model from each; rotation
   and translation from the first, scale from the ratio of inter-camera distances; score by
   rendering the model's silhouette in every view.
3. The best distinct candidates are refined briefly (Nelder-Mead over rotation, translation and
   log-scale about the model centre); the best pose of each model near the top is refined fully,
   and the best of those wins. Other models that end within AMBIGUOUS_GAP are reported as ties.

Score: per view, half IoU and half an edge term exp(-chamfer / tau) on the silhouette boundaries
(`Scorer`). IoU alone collapses for thin parts (rings, wire forms, forks) a few pixels off; the
contour distance keeps a slope the search can follow.

Scale: the library is metric. On a metric rig (`rig_metres_per_unit` known, from the capture's
`units`) the scale is a measurement: candidates and refinement stay within the part's size
tolerance (`scale_band`), a wrong-size look-alike loses, and the result states the measured size
deviation. Otherwise the scale comes from the data, anywhere in SCALE_SEARCH, and a look-alike
at another size is a tie.

The known part (`known_part_register`): no library search; the previous part's pose is the prior,
the search is the part's yaw about the conveyor normal and its position, then a local refinement.

Every result carries the object's pose in each camera (T_cam_obj) with an uncertainty from the
objective's curvature (`pose_sigmas`, `camera_poses`).

Hard cases: one view or coincident camera centres (the rig-to-object scale is unobservable from
images: it is the metric unit when known, else 1, and the distance to the object comes from the
mask size against the model size); masks touching the image border (their bbox is truncated, so
they generate no hypotheses while any untruncated view exists, but they are still scored);
near-symmetric objects (the best distinct pose and the score gap are reported; with images, the
pose whose colours agree better across views is preferred); nothing above threshold
(RegistrationError naming the best IoU found).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numba
import numpy as np
from scipy.optimize import minimize

from calibration.camera import Camera
from calibration.capture import Capture, capture_fingerprint, rig_metres_per_unit
from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix, geodesic_angle_deg, rotation_between
from reconstruction.library import Library
from reconstruction.parallel import num_threads, parallel_for
from reconstruction.silhouette import closed_winding, fill_triangles, normalize_silhouette, pack
from reconstruction.silhouette_index import ANGLE, BX, BY, EXTENT, SilhouetteIndex

# Below this anisotropy the principal axis of a mask is unreliable; such masks are tried at many rolls.
ISOTROPIC = 0.25
ISOTROPIC_ROLLS = 24
# Longest image side used when scoring hypotheses and when refining.
SCORE_PX = 128
REFINE_PX = 192
# Two poses closer than this are "the same pose" for the ambiguity report.
DISTINCT_DEG = 20.0
# Objective gap under which two poses (or two models) are reported as a near-tie.
AMBIGUOUS_GAP = 0.03
# Distinct (model, pose) candidates refined briefly before the winner is chosen.
CANDIDATES = 8
# Models (at most CONTENDERS) whose briefly refined objective is within TIE_SCREEN of the best are
# refined fully before the winner and any look-alike tie are decided.
CONTENDERS = 3
TIE_SCREEN = 0.15
# Objective = (1 - EDGE_WEIGHT) IoU + EDGE_WEIGHT exp(-chamfer / tau): half area, half contour,
# so a thick part is still judged mostly by area while a thin one keeps a smooth score.
EDGE_WEIGHT = 0.5
# tau = EDGE_TAU x the observed silhouette's bbox diagonal (px), at least EDGE_TAU_MIN_PX: the
# edge term halves when the contours are ~2 % of the object's image size apart on average.
EDGE_TAU = 0.03
EDGE_TAU_MIN_PX = 1.0
# Default tolerance of a part's size against its CAD model on a metric rig (±10 %).
SCALE_TOLERANCE = 0.10
# Rig-to-object scales considered when the rig's scale is unknown: six decades, any unit a
# calibration (metres, millimetres, an SfM frame normalised to the camera spread) can have.
SCALE_SEARCH = (1e-3, 1e3)
# Pose uncertainty: the objective drop that counts as "indistinguishable" (about the objective's
# change for a one-pixel contour shift at REFINE_PX), the probe step (rad / model radii) and the
# cap for a direction the silhouettes do not constrain.
UNCERTAINTY_DROP = 0.005
UNCERTAINTY_PROBE = 0.01
UNCERTAINTY_MAX = 0.5
# Photo-consistency z-buffer cell (px), and the ratio of colour disagreements below which the
# images overrule the silhouettes on a near-tie (a 10 % better agreement; on rig_scenes smaller
# differences went either way).
PHOTO_CELL_PX = 2
PHOTO_DECISIVE = 0.9
# Known-part path: yaw samples on the conveyor (15 deg apart), the longest image side they are
# scored at, how many yaws are refined (in yaw and position; a runner-up only within
# KNOWN_START_GAP of the best, as for a near-symmetric part) and with how many evaluations, and
# the image side and evaluations of the final full-pose refinement.
KNOWN_YAWS = 24
KNOWN_SCORE_PX = 96
KNOWN_STARTS = 2
KNOWN_START_GAP = 0.05
KNOWN_STAGE_EVALS = 30
KNOWN_FINAL_PX = 128
KNOWN_FINAL_EVALS = 60


class RegistrationError(ValueError):
    """Masks and library that do not determine a registration (one plain sentence)."""


@dataclass
class RegistrationResult:
    model_id: str
    sim3_rig_to_object: Sim3
    per_view_iou: np.ndarray
    score: float
    alternatives: list[tuple[str, float]]
    ambiguity: dict | None
    timings_s: dict
    truncated_views: list[int] = field(default_factory=list)
    scale_observable: bool = True
    objective: float | None = None
    rig_metres_per_unit: float | None = None
    scale_band: tuple[float, float] = SCALE_SEARCH
    model_ties: list[dict] = field(default_factory=list)
    camera_poses: list[dict] = field(default_factory=list)

    @property
    def part_scale_vs_cad(self) -> float | None:
        """Measured size of the part over its CAD model's (metric rig only): metres per rig unit / scale."""
        if self.rig_metres_per_unit is None:
            return None
        return self.rig_metres_per_unit / self.sim3_rig_to_object.scale

    def scale_statement(self) -> str:
        """One sentence on what the registration's scale means."""
        ratio = self.part_scale_vs_cad
        if ratio is None:
            return "the rig's scale is unknown, so the part's size is not measured"
        pct = (ratio - 1.0) * 100
        word = "larger" if pct >= 0 else "smaller"
        return f"the part is {abs(pct):.1f} % {word} than its CAD model"

    def to_dict(self) -> dict:
        return {
            "model_id": self.model_id,
            "sim3_rig_to_object": self.sim3_rig_to_object.to_dict(),
            "score": self.score,
            "objective": self.objective,
            "per_view_iou": self.per_view_iou.tolist(),
            "alternatives": [{"model_id": m, "score": s} for m, s in self.alternatives],
            "model_ties": self.model_ties,
            "ambiguity": self.ambiguity,
            "scale": {
                "metric": self.rig_metres_per_unit is not None,
                "rig_metres_per_unit": self.rig_metres_per_unit,
                "band": list(self.scale_band),
                "part_scale_vs_cad": self.part_scale_vs_cad,
                "statement": self.scale_statement(),
            },
            "camera_poses": self.camera_poses,
            "truncated_views": self.truncated_views,
            "scale_observable": self.scale_observable,
            "timings_s": self.timings_s,
        }

    @classmethod
    def from_dict(cls, doc: dict, *, capture: Capture | None = None, library: Library | None = None,
                  where: str = "the registration") -> RegistrationResult:
        """The result `to_dict` wrote (reg.json, the service's registration.json), checked against the
        `capture` and `library` it is to be used with when given (and the `provenance` the document
        records). A malformed or mismatched document raises RegistrationError in one sentence."""
        if not isinstance(doc, dict):
            raise RegistrationError(f"{where} is not a registration document: it holds a JSON {type(doc).__name__}, not an object")
        try:
            scale = doc["scale"]
            reg = cls(
                model_id=_typed(doc["model_id"], str),
                sim3_rig_to_object=Sim3.from_dict(doc["sim3_rig_to_object"]),
                per_view_iou=np.asarray(doc["per_view_iou"], np.float64).reshape(-1),
                score=float(doc["score"]),
                alternatives=[(_typed(a["model_id"], str), float(a["score"])) for a in doc["alternatives"]],
                ambiguity=None if doc["ambiguity"] is None else _typed(doc["ambiguity"], dict),
                timings_s=_typed(doc["timings_s"], dict),
                truncated_views=[int(v) for v in doc["truncated_views"]],
                scale_observable=_typed(doc["scale_observable"], bool),
                objective=None if doc["objective"] is None else float(doc["objective"]),
                rig_metres_per_unit=None if scale["rig_metres_per_unit"] is None else float(scale["rig_metres_per_unit"]),
                scale_band=tuple(float(b) for b in scale["band"]),
                model_ties=[_typed(t, dict) for t in doc["model_ties"]],
                camera_poses=[_typed(p, dict) for p in doc["camera_poses"]],
            )
        except KeyError as e:
            raise RegistrationError(f"{where} is not a registration document: it has no {e.args[0]!r}") from None
        except (TypeError, ValueError, AttributeError) as e:
            raise RegistrationError(f"{where} is not a registration document: {e}") from None
        if len(reg.scale_band) != 2 or not np.all(np.isfinite(reg.per_view_iou)):
            raise RegistrationError(f"{where} is not a registration document: its scale band or per-view IoUs are malformed")
        if capture is not None:
            check_fits(reg, capture, where)
            views = [f.file_path for f in capture.frames]
            if doc.get("views", views) != views or doc.get("capture_sha256", capture_fingerprint(capture)) != capture_fingerprint(capture):
                raise RegistrationError(f"{where} was made from another capture than the one at {capture.root}")
        if library is not None:
            if reg.model_id not in library.ids:
                raise RegistrationError(f"{where} registers model {reg.model_id!r}, which is not in the library at {library.root}")
            if doc.get("model_sha256", library.entry(reg.model_id).sha256) != library.entry(reg.model_id).sha256:
                raise RegistrationError(f"{where} was made with another library: its {reg.model_id!r} is not the mesh in {library.root}")
        return reg


def provenance(capture: Capture, library: Library, model_id: str) -> dict:
    """What a registration document records beside `to_dict()` so `from_dict` can refuse it for another
    capture or library: the views' file paths, the capture's fingerprint, the model mesh's sha256."""
    return {"views": [f.file_path for f in capture.frames], "capture_sha256": capture_fingerprint(capture),
            "model_sha256": library.entry(model_id).sha256}


def check_fits(reg: RegistrationResult, capture: Capture, where: str = "the registration") -> None:
    """Refuse (RegistrationError, one sentence) a registration of another number of views than `capture`
    has, or one made without the metric scale the capture states (or with one it does not)."""
    if len(reg.per_view_iou) != len(capture):
        raise RegistrationError(f"{where} registers {len(reg.per_view_iou)} camera views but the capture at {capture.root} has {len(capture)}")
    metric = rig_metres_per_unit(capture.meta, capture.root)
    if reg.rig_metres_per_unit != metric:
        stated = "no metric scale" if reg.rig_metres_per_unit is None else f"{reg.rig_metres_per_unit:g} m per rig unit"
        raise RegistrationError(f"{where} was registered with {stated}, but the capture at {capture.root} states "
                                + ("none" if metric is None else f"{metric:g} m per rig unit"))


def _typed(value, kind: type):
    if not isinstance(value, kind):
        raise TypeError(f"{value!r} is not a {kind.__name__}")
    return value


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


def sim3_from_pair(first: Hypothesis, second: Hypothesis | None, cameras: list[Camera], center: np.ndarray, *,
                   band: tuple[float, float] = SCALE_SEARCH, expected_scale: float | None = None) -> list[Sim3]:
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


# --- silhouette scoring ------------------------------------------------------------------------


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
                edge = r == 0 or c == 0 or r == h - 1 or c == w - 1 or not sil[r - 1, c] or not sil[r + 1, c] or not sil[r, c - 1] or not sil[r, c + 1]
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
def _view_scores(lo: int, hi: int, verts: np.ndarray, faces: np.ndarray, winding: int, ks: np.ndarray, viewmats: np.ndarray, masks: np.ndarray,
                 obs_dt: np.ndarray, obs_edges: np.ndarray, n_edges: np.ndarray, obs_boxes: np.ndarray, sizes: np.ndarray, counts: np.ndarray,
                 taus: np.ndarray, edge_weight: float, stop_below: float, iou: np.ndarray, obj: np.ndarray) -> None:
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
    cross = cv2.erode(mask.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3)), borderType=cv2.BORDER_CONSTANT, borderValue=0)
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

    def scores(self, vertices_obj: np.ndarray, faces: np.ndarray, sim3_rig_to_object: Sim3, *, stop_below: float = -1.0,
               parallel: bool = True, winding: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """IoU [V] and objective [V] of the mesh (object frame) seen by the rig cameras under the Sim(3).

        With `stop_below`, scoring stops once the objective sum cannot reach it (the rest stay 0).
        `parallel=False` keeps the work on the calling thread (for callers that score several poses at once).
        `winding`: the mesh's `closed_winding`, when known: a closed mesh's silhouettes are drawn from half its faces.
        """
        s, r, t = sim3_rig_to_object.scale, sim3_rig_to_object.rotation, sim3_rig_to_object.translation
        verts_rig = ((vertices_obj - t) @ r) / s
        n = len(self.ks)
        iou, obj = np.zeros(n), np.zeros(n)
        args = (verts_rig, faces, int(winding), self.ks, self.viewmats, self.masks, self.obs_dt, self.obs_edges, self.n_edges, self.obs_boxes,
                self.sizes, self.counts, self.taus, self.edge_weight)
        if stop_below > -1.0 or not parallel:
            # Cutting short depends on the running sum over the views in order: one thread.
            _view_scores(0, n, *args, float(stop_below), iou, obj)
        else:
            # Views are independent: any split over the threads gives the same scores.
            parallel_for(_view_scores, n, *args, -1.0, iou, obj)
        return iou, obj

    def __call__(self, vertices_obj: np.ndarray, faces: np.ndarray, sim3_rig_to_object: Sim3, *, stop_below: float = -1.0,
                 winding: int = 0) -> np.ndarray:
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


def _score_candidates(scorer: Scorer, candidates: list[tuple[int, Sim3]], mesh) -> list[tuple[float, int, Sim3]]:
    """(mean objective, model, Sim(3)) of each candidate, in order, as if scored one after another with the
    ones that cannot enter the top CANDIDATES so far cut short.

    The bar only rises, so a batch scored in parallel against the bar before it has computed every view that
    the bar of its own turn would have (`cut_short` then stops it there): the scores are those of the
    sequential loop for any thread count.
    """
    scored: list[tuple[float, int, Sim3]] = []
    n_views = len(scorer.ks)
    batch = 2 * num_threads()
    shapes = {model: mesh(model) for model, _ in candidates}  # loaded here, not on the scoring threads

    def bar() -> float:
        return sorted(s[0] for s in scored)[-CANDIDATES] * n_views if len(scored) >= CANDIDATES else -1.0

    for start in range(0, len(candidates), batch):
        chunk = candidates[start : start + batch]
        objs: list[np.ndarray | None] = [None] * len(chunk)
        stale = bar()

        def score(lo: int, hi: int) -> None:
            for i in range(lo, hi):
                model, sim = chunk[i]
                verts, faces, winding = shapes[model]
                objs[i] = scorer.scores(verts, faces, sim, stop_below=stale, parallel=False, winding=winding)[1]

        parallel_for(score, len(chunk))
        for (model, sim), obj in zip(chunk, objs):
            scored.append((float(cut_short(obj, bar()).mean()), model, sim))
    return scored


def perturb(sim3: Sim3, params: np.ndarray, center: np.ndarray, radius: float) -> Sim3:
    """Sim(3) moved by 7 params (rotation vector, translation in model radii, log-scale) about the model centre, in the object frame."""
    rot = axis_angle_to_matrix(params[:3])
    s = float(np.exp(params[6]))
    delta = Sim3(s, rot, center + radius * params[3:6] - s * rot @ center)
    return delta @ sim3


def scale_band(rig_metres_per_unit: float | None, tolerance: float = SCALE_TOLERANCE) -> tuple[float, float]:
    """Allowed rig-to-object scales (the library is in metres).

    Metric rig (`rig_metres_per_unit` known): the part may differ from its CAD model by
    ±`tolerance` in size, so s = metres per rig unit / size ratio lies in
    [m / (1 + tol), m / (1 - tol)]. Unknown scale: SCALE_SEARCH, any scale a calibration can have.
    """
    if rig_metres_per_unit is None:
        return SCALE_SEARCH
    if not 0.0 <= tolerance < 1.0:
        raise RegistrationError(f"the scale tolerance must be in [0, 1), got {tolerance}")
    m = float(rig_metres_per_unit)
    return m / (1.0 + tolerance), m / (1.0 - tolerance)


def _in_band(sim3: Sim3, band: tuple[float, float]) -> bool:
    return band[0] * (1 - 1e-9) <= sim3.scale <= band[1] * (1 + 1e-9)


def refine(scorer: Scorer, verts: np.ndarray, faces: np.ndarray, sim3: Sim3, center: np.ndarray, radius: float, *, max_evals: int = 200,
           fix_scale: bool = False, band: tuple[float, float] = SCALE_SEARCH, basis: np.ndarray | None = None, steps: np.ndarray | None = None,
           winding: int = 0) -> tuple[Sim3, float]:
    """Local Nelder-Mead on the mean silhouette objective; returns the refined Sim(3) and its objective.

    The search runs over x with the 7 perturbation params = basis [7, n] @ x (default: all 7, or the
    first 6 with `fix_scale`); poses whose scale leaves `band` are refused. `winding`: see `Scorer.scores`.
    """
    if basis is None:
        basis = np.eye(7)[:, :6] if fix_scale else np.eye(7)
        steps = np.array([0.06, 0.06, 0.06, 0.04, 0.04, 0.04, 0.04])[: basis.shape[1]]
    n = basis.shape[1]

    def cost(x):
        cand = perturb(sim3, basis @ x, center, radius)
        if not _in_band(cand, band):
            return 1.0
        return -float(scorer.scores(verts, faces, cand, winding=winding)[1].mean())

    simplex = np.vstack([np.zeros(n), np.diag(steps)])
    res = minimize(cost, np.zeros(n), method="Nelder-Mead", options={"initial_simplex": simplex, "maxfev": max_evals, "xatol": 1e-4, "fatol": 1e-5})
    start = -cost(np.zeros(n))
    if -res.fun < start:
        return sim3, start
    return perturb(sim3, basis @ res.x, center, radius), -float(res.fun)


# --- pose per camera, and its uncertainty -----------------------------------------------------


def pose_sigmas(scorer: Scorer, verts: np.ndarray, faces: np.ndarray, sim3: Sim3, center: np.ndarray, radius: float, *,
                winding: int = 0) -> np.ndarray:
    """Standard deviations [6] of the rotation vector (rad) and translation (model radii) perturbations.

    Each is the offset at which the mean objective drops by UNCERTAINTY_DROP, from a quadratic
    through the optimum and probes at ±UNCERTAINTY_PROBE (a flat direction is capped at
    UNCERTAINTY_MAX): the pose changes the silhouettes cannot tell apart from the registered one.
    """
    f0 = float(scorer.scores(verts, faces, sim3, winding=winding)[1].mean())
    out = np.zeros(6)
    for i in range(6):
        d = np.zeros(7)
        d[i] = UNCERTAINTY_PROBE
        fp = float(scorer.scores(verts, faces, perturb(sim3, d, center, radius), winding=winding)[1].mean())
        fm = float(scorer.scores(verts, faces, perturb(sim3, -d, center, radius), winding=winding)[1].mean())
        curv = (2.0 * f0 - fp - fm) / UNCERTAINTY_PROBE**2
        out[i] = min(np.sqrt(2.0 * UNCERTAINTY_DROP / curv), UNCERTAINTY_MAX) if curv > 0 else UNCERTAINTY_MAX
    return out


def camera_poses(cameras_rig: list[Camera], sim3: Sim3, sigmas: np.ndarray, center: np.ndarray, radius: float, *, samples: int = 64, seed: int = 0) -> list[dict]:
    """The object's pose in every camera, T_cam_obj [4, 4] (x_cam = T_cam_obj x_obj, object units), with
    its uncertainty: RMS rotation (deg) and translation (object units) over Sim(3) perturbations drawn
    from N(0, diag(`sigmas`^2)) (see `pose_sigmas`)."""
    rng = np.random.default_rng(seed)
    c2w_rig = np.stack([c.c2w for c in cameras_rig])
    t_cam_obj = np.linalg.inv(sim3.apply_to_c2w(c2w_rig))
    rot = np.zeros((samples, len(cameras_rig)))
    trans = np.zeros((samples, len(cameras_rig)))
    for i in range(samples):
        d = perturb(sim3, np.concatenate([rng.normal(size=6) * sigmas, [0.0]]), center, radius)
        t_d = np.linalg.inv(d.apply_to_c2w(c2w_rig))
        rot[i] = geodesic_angle_deg(t_d[:, :3, :3], t_cam_obj[:, :3, :3])
        trans[i] = np.linalg.norm(t_d[:, :3, 3] - t_cam_obj[:, :3, 3], axis=1)
    rot_sigma, trans_sigma = np.sqrt(np.mean(rot**2, 0)), np.sqrt(np.mean(trans**2, 0))
    return [{"T_cam_obj": t.tolist(), "rotation_sigma_deg": float(r), "translation_sigma": float(s)} for t, r, s in zip(t_cam_obj, rot_sigma, trans_sigma)]


# --- image evidence for near-ties --------------------------------------------------------------


def photo_disagreement(images: np.ndarray, cameras_rig: list[Camera], verts: np.ndarray, faces: np.ndarray, sim3: Sim3) -> float:
    """How much the views disagree on the colour of the model's surface under a pose (lower = the
    images agree better): per surface point the median absolute deviation of its colour across the
    views that see it (at least three), summed over RGB, averaged over points. `images` [V, H, W, 3]
    float in [0, 1].

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
        h, w = images[v].shape[:2]
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
        cols[v, seen] = bilinear(images[v], uv[seen])
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


def rig_up(cameras_rig: list[Camera]) -> np.ndarray:
    """The rig's up direction [3] (rig frame): the mean of the cameras' up axes (-y in OpenCV).
    Rig cameras are mounted upright around a conveyor, so their up axes agree on the conveyor normal."""
    ups = np.array([-c.c2w[:3, 1] for c in cameras_rig])
    u = ups.sum(0)
    n = np.linalg.norm(u)
    if n < 1e-9:
        raise RegistrationError("the cameras' up axes cancel out; give the conveyor's up direction")
    return u / n


def area_centroid(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted centroid [3] of a triangle mesh: where silhouette centroids from around it meet."""
    tri = verts[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return (tri.mean(1) * area[:, None]).sum(0) / max(float(area.sum()), 1e-300)


def triangulate_centroid(masks: np.ndarray, cameras_rig: list[Camera]) -> np.ndarray | None:
    """Least-squares meeting point [3] (rig frame) of the rays through the masks' centroids; None with fewer than two usable views."""
    a, b, used = np.zeros((3, 3)), np.zeros(3), 0
    for m, cam in zip(masks, cameras_rig):
        ys, xs = np.nonzero(m)
        if len(xs) == 0 or touches_border(m):
            continue
        d = cam.c2w[:3, :3] @ np.linalg.solve(cam.K, [xs.mean() + 0.5, ys.mean() + 0.5, 1.0])
        d /= np.linalg.norm(d)
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ cam.center
        used += 1
    if used < 2 or np.linalg.cond(a) > 1e8:
        return None
    return np.linalg.solve(a, b)


# --- the registration ------------------------------------------------------------------------


def match_views(observations: list[Observation | None], index: SilhouetteIndex, *, top_k: int, iou_threshold: float, model_mask: np.ndarray | None) -> tuple[list[list[Hypothesis]], float]:
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


def independent_poses(masks: np.ndarray, cameras: list[Camera], library: Library, *, model_ids: list[str] | None = None) -> list[tuple[str, np.ndarray] | None]:
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


def _check_inputs(masks: np.ndarray, cameras_rig: list[Camera]) -> np.ndarray:
    masks = np.asarray(masks, dtype=bool)
    if masks.ndim != 3 or len(masks) != len(cameras_rig) or len(masks) == 0:
        raise RegistrationError(f"register needs one [H, W] mask per camera, got masks {masks.shape} for {len(cameras_rig)} cameras")
    for i, (m, c) in enumerate(zip(masks, cameras_rig)):
        # Views of mixed sizes share a canvas, each top-left, with nothing of its mask outside its camera.
        if m.shape[0] < c.height or m.shape[1] < c.width or m.sum() != c.crop(m).sum():
            raise RegistrationError(f"mask {i} is {m.shape[1]}x{m.shape[0]} but its camera is {c.width}x{c.height}")
    if not masks.any():
        raise RegistrationError("every mask is empty; there is no object to register")
    return masks


def _finish(masks, cameras_rig, library, model: int, refined: Sim3, objective: float, fine: Scorer, *, alternatives, ambiguity, model_ties, timings,
            t0, truncated, scale_observable, rig_metres_per_unit, band) -> RegistrationResult:
    """The result of a registration: per-view IoU at full resolution, the pose per camera with its
    uncertainty (from the objective of `fine`, the scorer the pose was refined on)."""
    index = library.index
    verts, faces, winding = scoring_shape(library, index.model_ids[model])
    center, radius = index.centers[model], float(index.radii[model])
    t = time.perf_counter()
    full = Scorer(masks, cameras_rig, max(max(c.width, c.height) for c in cameras_rig), edge_weight=0.0)
    per_view = full(verts, faces, refined, winding=winding)
    sigmas = pose_sigmas(fine, verts, faces, refined, center, radius, winding=winding)
    timings["poses"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t0
    return RegistrationResult(
        model_id=index.model_ids[model],
        sim3_rig_to_object=refined,
        per_view_iou=per_view,
        score=float(per_view.mean()),
        alternatives=alternatives,
        ambiguity=ambiguity,
        timings_s={k: round(v, 4) for k, v in timings.items()},
        truncated_views=truncated,
        scale_observable=scale_observable,
        objective=float(objective),
        rig_metres_per_unit=rig_metres_per_unit,
        scale_band=band,
        model_ties=model_ties,
        camera_poses=camera_poses(cameras_rig, refined, sigmas, center, radius),
    )


def register(
    masks: np.ndarray,
    cameras_rig: list[Camera],
    library: Library,
    *,
    top_k: int = 50,
    iou_threshold: float = 0.7,
    seed: int = 0,
    model_ids: list[str] | None = None,
    iterations: int = 300,
    refine_evals: int = 200,
    rig_metres_per_unit: float | None = None,
    scale_tolerance: float = SCALE_TOLERANCE,
    images: np.ndarray | None = None,
) -> RegistrationResult:
    """Best library model and rig-to-object Sim(3) for bool masks [V, H, W] from pinhole rig cameras.

    `rig_metres_per_unit`: the rig frame's unit in metres when its calibration is metric (1.0 for
    `units: m`); the scale is then a measurement held to ±`scale_tolerance` of the part's size.
    None: the rig's scale is unknown and searched over SCALE_SEARCH. `images` [V, H, W, 3] float in
    [0, 1], when given, break near-ties between poses by colour agreement across views.
    """
    t0 = time.perf_counter()
    masks = _check_inputs(masks, cameras_rig)
    band = scale_band(rig_metres_per_unit, scale_tolerance)
    index = library.index
    model_mask = None
    if model_ids is not None:
        keep = {m for m in model_ids}
        model_mask = np.array([m in keep for m in index.model_ids])
        if not model_mask.any():
            raise RegistrationError(f"none of the requested models ({', '.join(sorted(keep))}) is in the library")
    rng = np.random.default_rng(seed)
    timings = {}

    observations = [observe(m, c, index.grid.canvas) for m, c in zip(masks, cameras_rig)]
    truncated = [i for i, o in enumerate(observations) if o is not None and o.truncated]
    timings["observe"] = time.perf_counter() - t0
    t = time.perf_counter()
    hyps, best_seen = match_views(observations, index, top_k=top_k, iou_threshold=iou_threshold, model_mask=model_mask)
    timings["match"] = time.perf_counter() - t
    if not any(hyps):
        raise RegistrationError(f"no library silhouette reaches IoU {iou_threshold:.2f} with any mask; the best IoU found was {best_seen:.2f}")

    # Truncated silhouettes have a wrong bbox: they seed hypotheses only when nothing else can.
    seeds = [v for v, h in enumerate(hyps) if h and v not in truncated] or [v for v, h in enumerate(hyps) if h]
    centers = np.array([c.center for c in cameras_rig])
    spread = float(np.linalg.norm(centers - centers.mean(0), axis=1).max()) if len(centers) > 1 else 0.0
    scale_observable = spread > 1e-9 * max(1.0, float(np.abs(centers).max()))
    # A metric rig's scale is known up to the part's tolerance; without baselines and units it is set to 1.
    expected = None if rig_metres_per_unit is None else float(rig_metres_per_unit)

    t = time.perf_counter()
    scorer = Scorer(masks, cameras_rig, SCORE_PX)
    meshes: dict[int, tuple[np.ndarray, np.ndarray, int]] = {}

    def mesh(model: int):
        if model not in meshes:
            meshes[model] = scoring_shape(library, index.model_ids[model])
        return meshes[model]

    scored: list[tuple[float, int, Sim3]] = []
    by_model_view: dict[tuple[int, int], list[Hypothesis]] = {}
    for v, hs in enumerate(hyps):
        for h in hs:
            by_model_view.setdefault((h.model, v), []).append(h)
    seen = set()
    candidates: list[tuple[int, Sim3]] = []
    for _ in range(iterations):
        vi = seeds[rng.integers(len(seeds))]
        hi = hyps[vi][rng.integers(len(hyps[vi]))]
        second, key2 = None, None
        if scale_observable:
            partners = [v for v in range(len(hyps)) if v != vi and (hi.model, v) in by_model_view and np.linalg.norm(centers[v] - centers[vi]) > 1e-9 * max(1.0, spread)]
            if not partners:
                continue
            vj = partners[rng.integers(len(partners))]
            cands = by_model_view[(hi.model, vj)]
            j = int(rng.integers(len(cands)))
            second, key2 = cands[j], (vj, j)
        key = (id(hi), key2)
        if key in seen:
            continue
        seen.add(key)
        candidates += [(hi.model, sim) for sim in sim3_from_pair(hi, second, cameras_rig, index.centers[hi.model], band=band,
                                                                expected_scale=expected)]
    scored += _score_candidates(scorer, candidates, mesh)
    if not scored:
        # Every hypothesising model appears in one view only: no pair to take a scale from.
        for vi in seeds:
            for h in hyps[vi][:top_k]:
                sim = sim3_from_pair(h, None, cameras_rig, index.centers[h.model], band=band, expected_scale=expected)[0]
                v_, f_, w_ = mesh(h.model)
                scored.append((float(scorer.scores(v_, f_, sim, winding=w_)[1].mean()), h.model, sim))
    timings["ransac"] = time.perf_counter() - t
    scored.sort(key=lambda s: -s[0])

    # A discrete grid lets a near-symmetric wrong pose outscore the right one before refinement,
    # so the best few distinct candidates are refined briefly and the best after that wins.
    t = time.perf_counter()
    fix_scale = not scale_observable
    shortlist: list[tuple[float, int, Sim3]] = []
    for sc, m, sim in scored:
        if len(shortlist) == CANDIDATES:
            break
        if all(m != o[1] or geodesic_angle_deg(sim.rotation, o[2].rotation) > DISTINCT_DEG for o in shortlist):
            v_, f_, w_ = mesh(m)
            sim_r, sc_r = refine(scorer, v_, f_, sim, index.centers[m], float(index.radii[m]), max_evals=refine_evals // 4, fix_scale=fix_scale, band=band,
                                 winding=w_)
            shortlist.append((sc_r, m, sim_r))
    shortlist.sort(key=lambda s: -s[0])
    # The best pose of each model close to the top gets the full refinement: a look-alike (another
    # model that fits as well) is then either the winner or reported as a tie, not lost to a brief refinement.
    fine = Scorer(masks, cameras_rig, REFINE_PX)
    contenders: list[tuple[float, int, Sim3]] = []
    for sc, m, sim in shortlist:
        if sc >= shortlist[0][0] - TIE_SCREEN and all(m != c[1] for c in contenders) and len(contenders) < CONTENDERS:
            v_, f_, w_ = mesh(m)
            sim_r, sc_r = refine(fine, v_, f_, sim, index.centers[m], float(index.radii[m]), max_evals=refine_evals, fix_scale=fix_scale, band=band,
                                 winding=w_)
            contenders.append((sc_r, m, sim_r))
    contenders.sort(key=lambda c: -c[0])
    (score, best_model, refined) = contenders[0]
    # cad_size_ratio: the tied model's size over the winner's; scale_ratio: the rig-to-object scale
    # it fits at over the winner's. Both equal: the same shape at another size, which only a metric rig tells apart.
    model_ties = [
        {"model_id": index.model_ids[m], "score_gap": float(score - sc), "cad_size_ratio": float(index.radii[m] / index.radii[best_model]),
         "scale_ratio": float(sim.scale / refined.scale)}
        for sc, m, sim in contenders[1:] if score - sc < AMBIGUOUS_GAP
    ]
    verts, faces, winding = mesh(best_model)
    center, radius = index.centers[best_model], float(index.radii[best_model])

    # The best pose of the same model that is not the same pose: the symmetry report.
    ambiguity = None
    alt = next((s for s in shortlist + scored if s[1] == best_model and geodesic_angle_deg(s[2].rotation, refined.rotation) > DISTINCT_DEG), None)
    if alt is not None:
        alt_sim, alt_score = refine(fine, verts, faces, alt[2], center, radius, max_evals=refine_evals // 2, fix_scale=fix_scale, band=band,
                                    winding=winding)
        if alt_score > score:
            refined, score, alt_sim, alt_score = alt_sim, alt_score, refined, score
        gap = score - alt_score
        ambiguity = {
            "ambiguous": bool(gap < AMBIGUOUS_GAP),
            "score_gap": float(gap),
            "alternative_score": float(alt_score),
            "rotation_deg": float(geodesic_angle_deg(alt_sim.rotation, refined.rotation)),
            "alternative_sim3_rig_to_object": alt_sim.to_dict(),
        }
        if ambiguity["ambiguous"] and images is not None:
            pd, pd_alt = photo_disagreement(images, cameras_rig, verts, faces, refined), photo_disagreement(images, cameras_rig, verts, faces, alt_sim)
            decisive = bool(pd_alt < PHOTO_DECISIVE * pd)
            if decisive:
                # The images overrule the silhouettes (score_gap turns negative).
                ambiguity["alternative_sim3_rig_to_object"] = refined.to_dict()
                refined, score, alt_score, pd, pd_alt = alt_sim, alt_score, score, pd_alt, pd
                ambiguity["score_gap"], ambiguity["alternative_score"] = float(score - alt_score), float(alt_score)
            ambiguity.update(photo_disagreement=pd, alternative_photo_disagreement=pd_alt, decided_by="images" if decisive else "silhouettes")
    timings["refine"] = time.perf_counter() - t

    per_model: dict[int, float] = {}
    for s, m, _ in scored:
        if m != best_model and s > per_model.get(m, -1.0):
            per_model[m] = s
    alternatives = [(index.model_ids[m], float(s)) for m, s in sorted(per_model.items(), key=lambda kv: -kv[1])[:5]]
    return _finish(masks, cameras_rig, library, best_model, refined, score, fine, alternatives=alternatives, ambiguity=ambiguity, model_ties=model_ties,
                   timings=timings, t0=t0, truncated=truncated, scale_observable=scale_observable, rig_metres_per_unit=rig_metres_per_unit, band=band)


def known_part_register(
    masks: np.ndarray,
    cameras_rig: list[Camera],
    library: Library,
    model_id: str,
    prior: Sim3 | None,
    *,
    rig_metres_per_unit: float | None = None,
    scale_tolerance: float = SCALE_TOLERANCE,
    up_rig: np.ndarray | None = None,
    seed: int = 0,
) -> RegistrationResult:
    """The known part again: no library search; the object lies on the conveyor as the previous one did.

    The search space is the part's pose on the conveyor: its yaw about the conveyor normal
    `up_rig` [3] (default: `rig_up`), KNOWN_YAWS of them, and its position (the masks' centroids
    triangulated); the previous part's rig-to-object Sim(3) `prior` gives its resting face and
    scale. The best few yaws are refined in yaw and position, the winner in full pose. Without a
    prior this is a full search restricted to `model_id`.
    """
    t0 = time.perf_counter()
    masks = _check_inputs(masks, cameras_rig)
    index = library.index
    if model_id not in index.model_ids:
        raise RegistrationError(f"the known part {model_id!r} is not in the library")
    if prior is None:
        return register(masks, cameras_rig, library, model_ids=[model_id], rig_metres_per_unit=rig_metres_per_unit, scale_tolerance=scale_tolerance, seed=seed)
    band = scale_band(rig_metres_per_unit, scale_tolerance)
    model = index.model_ids.index(model_id)
    verts, faces, winding = scoring_shape(library, model_id)
    center, radius = index.centers[model], float(index.radii[model])
    up = rig_up(cameras_rig) if up_rig is None else np.asarray(up_rig, np.float64) / np.linalg.norm(up_rig)
    s = float(np.clip(prior.scale, *band))
    # The model's area centroid where the previous part had it, and where this part's masks put it.
    ref = area_centroid(verts, faces)
    p_prev = prior.inverse().apply(ref[None])[0]
    p_now = triangulate_centroid(masks, cameras_rig)
    if p_now is None:
        p_now = p_prev
    base = Sim3(s, prior.rotation, ref - s * prior.rotation @ p_prev)
    timings = {"observe": time.perf_counter() - t0}

    t = time.perf_counter()
    scorer = Scorer(masks, cameras_rig, KNOWN_SCORE_PX)
    cands = []
    for yaw in np.arange(KNOWN_YAWS) * (2 * np.pi / KNOWN_YAWS):
        turn = axis_angle_to_matrix(yaw * up)
        # x_rig -> turned back about the triangulated centre onto the previous placement -> object.
        sim = base @ Sim3(1.0, turn.T, p_prev - turn.T @ p_now)
        cands.append((float(scorer.scores(verts, faces, sim, winding=winding)[1].mean()), sim))
    cands.sort(key=lambda c: -c[0])
    timings["yaw_search"] = time.perf_counter() - t

    t = time.perf_counter()
    best = None
    for sc, sim in [c for c in cands[:KNOWN_STARTS] if c[0] >= cands[0][0] - KNOWN_START_GAP]:
        # Yaw (about the conveyor normal, seen in the object frame) and position only.
        basis = np.zeros((7, 4))
        basis[:3, 0] = sim.rotation @ up
        basis[3:6, 1:] = np.eye(3)
        sim_r, sc_r = refine(scorer, verts, faces, sim, center, radius, max_evals=KNOWN_STAGE_EVALS, band=band, basis=basis,
                             steps=np.array([0.1, 0.05, 0.05, 0.05]), winding=winding)
        if best is None or sc_r > best[0]:
            best = (sc_r, sim_r)
    fine = Scorer(masks, cameras_rig, KNOWN_FINAL_PX)
    fix_scale = rig_metres_per_unit is None
    refined, score = refine(fine, verts, faces, best[1], center, radius, max_evals=KNOWN_FINAL_EVALS, fix_scale=fix_scale, band=band,
                            winding=winding)
    timings["refine"] = time.perf_counter() - t
    return _finish(masks, cameras_rig, library, model, refined, score, fine, alternatives=[], ambiguity=None, model_ties=[], timings=timings, t0=t0,
                   truncated=[i for i, m in enumerate(masks) if m.any() and touches_border(m)], scale_observable=True,
                   rig_metres_per_unit=rig_metres_per_unit, band=band)

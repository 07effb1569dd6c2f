"""Silhouette consensus registration of a calibrated rig to a CAD library (paper section 3.2).

1. Each observed mask is rotated to a virtual camera looking at its centroid (a homography, so
   the off-axis perspective is undone), normalised like the library silhouettes, and matched
   against the whole index: its top-k library views with IoU >= threshold are camera-to-object
   pose hypotheses (rotation from the grid direction plus the closed-form in-plane roll; distance
   from the silhouette's size; position from the bbox centre through the intrinsics).
2. RANSAC over Sim(3): sample two views and one hypothesis of the same model from each; rotation
   and translation from the first, scale from the ratio of inter-camera distances; score by
   rendering the model's silhouette in every view and averaging the IoUs.
3. The best (model, Sim(3)) is refined locally (Nelder-Mead over rotation, translation and
   log-scale about the model centre) on the silhouette IoU.

Hard cases: one view or coincident camera centres (the rig-to-object scale is unobservable from
images: it is set to 1, i.e. a metric rig and a metric library, and the distance to the object
comes from the mask size against the model size); masks touching the image border (their bbox is
truncated, so they generate no hypotheses while any untruncated view exists, but they are still
scored); near-symmetric objects (the best distinct pose and the score gap are reported); nothing
above threshold (RegistrationError naming the best IoU found).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numba
import numpy as np
from scipy.optimize import minimize

from calibration.camera import Camera
from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix, geodesic_angle_deg, rotation_between
from reconstruction.library import Library
from reconstruction.silhouette import fill_triangles, normalize_silhouette, pack
from reconstruction.silhouette_index import ANGLE, BX, BY, EXTENT, SilhouetteIndex

# Below this anisotropy the principal axis of a mask is unreliable; such masks are tried at many rolls.
ISOTROPIC = 0.25
ISOTROPIC_ROLLS = 24
# Longest image side used when scoring hypotheses and when refining.
SCORE_PX = 128
REFINE_PX = 192
# Two poses closer than this are "the same pose" for the ambiguity report.
DISTINCT_DEG = 20.0
AMBIGUOUS_GAP = 0.03
# Distinct (model, pose) candidates refined briefly before the winner is chosen.
CANDIDATES = 8


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

    def to_dict(self) -> dict:
        return {
            "model_id": self.model_id,
            "sim3_rig_to_object": self.sim3_rig_to_object.to_dict(),
            "score": self.score,
            "per_view_iou": self.per_view_iou.tolist(),
            "alternatives": [{"model_id": m, "score": s} for m, s in self.alternatives],
            "ambiguity": self.ambiguity,
            "truncated_views": self.truncated_views,
            "scale_observable": self.scale_observable,
            "timings_s": self.timings_s,
        }


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


def sim3_from_pair(first: Hypothesis, second: Hypothesis | None, cameras: list[Camera], center: np.ndarray) -> list[Sim3]:
    """Rig-to-object Sim(3) candidates: rotation and translation from `first`, scale from `second`.

    The paper's scale is the ratio of inter-camera distances |C_i - C_j|_obj / |C_i - C_j|_rig; it
    needs the second hypothesis's rotation right too. The second candidate scale only asks the
    second camera's distance to the model `center` to match its hypothesis (it depends on the
    silhouette's size, not its rotation), which makes a good first hypothesis enough. Without
    `second` the scale is 1.
    """
    ci = cameras[first.view]
    r = first.r_obj_cam @ ci.c2w[:3, :3].T
    scales = [1.0]
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
    return [Sim3(s, r, first.center_obj - s * r @ ci.center) for s in scales]


# --- silhouette scoring ------------------------------------------------------------------------


@numba.njit(cache=True, nogil=True)
def _view_ious(verts: np.ndarray, faces: np.ndarray, ks: np.ndarray, viewmats: np.ndarray, masks: np.ndarray, sizes: np.ndarray, counts: np.ndarray, stop_below: float) -> np.ndarray:
    """IoU per view; stops early (remaining views left at 0) once the sum cannot reach `stop_below`."""
    n_views = ks.shape[0]
    out = np.zeros(n_views)
    total = 0.0
    hmax, wmax = masks.shape[1], masks.shape[2]
    buf = np.zeros((hmax, wmax), dtype=np.bool_)
    uv = np.empty((verts.shape[0], 2))
    ok = np.empty(verts.shape[0], dtype=np.bool_)
    for v in range(n_views):
        h, w = sizes[v, 0], sizes[v, 1]
        vm = viewmats[v]
        k = ks[v]
        for i in range(verts.shape[0]):
            x = vm[0, 0] * verts[i, 0] + vm[0, 1] * verts[i, 1] + vm[0, 2] * verts[i, 2] + vm[0, 3]
            y = vm[1, 0] * verts[i, 0] + vm[1, 1] * verts[i, 1] + vm[1, 2] * verts[i, 2] + vm[1, 3]
            z = vm[2, 0] * verts[i, 0] + vm[2, 1] * verts[i, 1] + vm[2, 2] * verts[i, 2] + vm[2, 3]
            ok[i] = z > 1e-9
            zz = z if ok[i] else 1.0
            uv[i, 0] = k[0, 0] * x / zz + k[0, 1] * y / zz + k[0, 2]
            uv[i, 1] = k[1, 1] * y / zz + k[1, 2]
        view = buf[:h, :w]
        view[:, :] = False
        fill_triangles(uv, faces, ok, view)
        inter = 0
        rendered = 0
        for r in range(h):
            for c in range(w):
                if buf[r, c]:
                    rendered += 1
                    if masks[v, r, c]:
                        inter += 1
        union = rendered + counts[v] - inter
        out[v] = inter / union if union > 0 else 0.0
        total += out[v]
        if total + (n_views - 1 - v) < stop_below:
            break
    return out


class Scorer:
    """Per-view silhouette IoU of a mesh under a rig-to-object Sim(3), on masks downscaled to `max_px`."""

    def __init__(self, masks: np.ndarray, cameras: list[Camera], max_px: int):
        small, ks, vms, sizes = [], [], [], []
        for m, cam in zip(masks, cameras):
            s = min(1.0, max_px / max(cam.width, cam.height))
            w, h = max(1, round(cam.width * s)), max(1, round(cam.height * s))
            c = cam.scaled(w, h)
            small.append(cv2.resize(m.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) >= 0.5)
            ks.append(c.K)
            vms.append(c.viewmat)
            sizes.append((h, w))
        hm, wm = max(s[0] for s in sizes), max(s[1] for s in sizes)
        self.masks = np.zeros((len(small), hm, wm), dtype=np.bool_)
        for i, m in enumerate(small):
            self.masks[i, : m.shape[0], : m.shape[1]] = m
        self.ks = np.array(ks)
        self.viewmats = np.array(vms)
        self.sizes = np.array(sizes, dtype=np.int64)
        self.counts = self.masks.reshape(len(small), -1).sum(1).astype(np.int64)

    def __call__(self, vertices_obj: np.ndarray, faces: np.ndarray, sim3_rig_to_object: Sim3, *, stop_below: float = -1.0) -> np.ndarray:
        """IoU per view [V] of the mesh (object frame) seen by the rig cameras under the Sim(3).

        With `stop_below`, scoring stops once the IoU sum cannot reach it (the rest stay 0).
        """
        s, r, t = sim3_rig_to_object.scale, sim3_rig_to_object.rotation, sim3_rig_to_object.translation
        verts_rig = ((vertices_obj - t) @ r) / s
        return _view_ious(verts_rig, faces, self.ks, self.viewmats, self.masks, self.sizes, self.counts, float(stop_below))


def perturb(sim3: Sim3, params: np.ndarray, center: np.ndarray, radius: float) -> Sim3:
    """Sim(3) moved by 7 params (rotation vector, translation in model radii, log-scale) about the model centre, in the object frame."""
    rot = axis_angle_to_matrix(params[:3])
    s = float(np.exp(params[6]))
    delta = Sim3(s, rot, center + radius * params[3:6] - s * rot @ center)
    return delta @ sim3


def refine(scorer: Scorer, verts: np.ndarray, faces: np.ndarray, sim3: Sim3, center: np.ndarray, radius: float, *, max_evals: int = 200, fix_scale: bool = False) -> tuple[Sim3, float]:
    """Local Nelder-Mead on the mean silhouette IoU; returns the refined Sim(3) and its score."""
    n = 6 if fix_scale else 7

    def params7(x):
        return np.concatenate([x, [0.0]]) if fix_scale else x

    def cost(x):
        return -float(scorer(verts, faces, perturb(sim3, params7(x), center, radius)).mean())

    steps = np.array([0.06, 0.06, 0.06, 0.04, 0.04, 0.04, 0.04])[:n]
    simplex = np.vstack([np.zeros(n), np.diag(steps)])
    res = minimize(cost, np.zeros(n), method="Nelder-Mead", options={"initial_simplex": simplex, "maxfev": max_evals, "xatol": 1e-4, "fatol": 1e-5})
    best = perturb(sim3, params7(res.x), center, radius)
    start = -cost(np.zeros(n))
    if -res.fun < start:
        return sim3, start
    return best, -float(res.fun)


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
) -> RegistrationResult:
    """Best library model and rig-to-object Sim(3) for bool masks [V, H, W] from pinhole rig cameras."""
    t0 = time.perf_counter()
    masks = np.asarray(masks, dtype=bool)
    if masks.ndim != 3 or len(masks) != len(cameras_rig) or len(masks) == 0:
        raise RegistrationError(f"register needs one [H, W] mask per camera, got masks {masks.shape} for {len(cameras_rig)} cameras")
    for i, (m, c) in enumerate(zip(masks, cameras_rig)):
        if m.shape != (c.height, c.width):
            raise RegistrationError(f"mask {i} is {m.shape[1]}x{m.shape[0]} but its camera is {c.width}x{c.height}")
    if not masks.any():
        raise RegistrationError("every mask is empty; there is no object to register")
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

    t = time.perf_counter()
    n_views = len(masks)
    scorer = Scorer(masks, cameras_rig, SCORE_PX)
    meshes: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def mesh(model: int):
        if model not in meshes:
            meshes[model] = library.scoring_mesh(index.model_ids[model])
        return meshes[model]

    scored: list[tuple[float, int, Sim3]] = []
    by_model_view: dict[tuple[int, int], list[Hypothesis]] = {}
    for v, hs in enumerate(hyps):
        for h in hs:
            by_model_view.setdefault((h.model, v), []).append(h)
    seen = set()
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
        v_, f_ = mesh(hi.model)
        for sim in sim3_from_pair(hi, second, cameras_rig, index.centers[hi.model]):
            # Candidates that cannot enter the current top few are cut short.
            bar = sorted(s[0] for s in scored)[-CANDIDATES] * n_views if len(scored) >= CANDIDATES else -1.0
            ious = scorer(v_, f_, sim, stop_below=bar)
            scored.append((float(ious.mean()), hi.model, sim))
    if not scored:
        # Every hypothesising model appears in one view only: no pair to take a scale from.
        for vi in seeds:
            for h in hyps[vi][:top_k]:
                sim = sim3_from_pair(h, None, cameras_rig, index.centers[h.model])[0]
                v_, f_ = mesh(h.model)
                scored.append((float(scorer(v_, f_, sim).mean()), h.model, sim))
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
            v_, f_ = mesh(m)
            sim_r, sc_r = refine(scorer, v_, f_, sim, index.centers[m], float(index.radii[m]), max_evals=refine_evals // 4, fix_scale=fix_scale)
            shortlist.append((sc_r, m, sim_r))
    shortlist.sort(key=lambda s: -s[0])
    best_model, best_sim = shortlist[0][1], shortlist[0][2]
    fine = Scorer(masks, cameras_rig, REFINE_PX)
    verts, faces = mesh(best_model)
    center, radius = index.centers[best_model], float(index.radii[best_model])
    refined, score = refine(fine, verts, faces, best_sim, center, radius, max_evals=refine_evals, fix_scale=fix_scale)

    # The best pose of the same model that is not the same pose: the symmetry report.
    ambiguity = None
    alt = next((s for s in shortlist + scored if s[1] == best_model and geodesic_angle_deg(s[2].rotation, refined.rotation) > DISTINCT_DEG), None)
    if alt is not None:
        alt_sim, alt_score = refine(fine, verts, faces, alt[2], center, radius, max_evals=refine_evals // 2, fix_scale=fix_scale)
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
    timings["refine"] = time.perf_counter() - t

    per_model: dict[int, float] = {}
    for s, m, _ in scored:
        if m != best_model and s > per_model.get(m, -1.0):
            per_model[m] = s
    alternatives = [(index.model_ids[m], float(s)) for m, s in sorted(per_model.items(), key=lambda kv: -kv[1])[:5]]
    per_view = Scorer(masks, cameras_rig, max(max(c.width, c.height) for c in cameras_rig))(verts, faces, refined)
    timings["total"] = time.perf_counter() - t0
    return RegistrationResult(
        model_id=index.model_ids[best_model],
        sim3_rig_to_object=refined,
        per_view_iou=per_view,
        score=float(per_view.mean()),
        alternatives=alternatives,
        ambiguity=ambiguity,
        timings_s={k: round(v, 4) for k, v in timings.items()},
        truncated_views=truncated,
        scale_observable=scale_observable,
    )

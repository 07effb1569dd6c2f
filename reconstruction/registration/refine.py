"""Local refinement of a registration, and the pose per camera with its uncertainty.

`refine` runs Nelder-Mead over rotation, translation and log-scale about the model centre;
`pose_sigmas` reads the pose's uncertainty off the objective's curvature, and `camera_poses` turns it
into the object's pose in each camera (T_cam_obj) with an RMS rotation and translation spread.
`result_of` assembles the `RegistrationResult` both entry points return.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.optimize import minimize

from calibration.camera import Camera
from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix, geodesic_angle_deg
from reconstruction.registration.result import SCALE_SEARCH, RegistrationResult
from reconstruction.registration.scale import in_band
from reconstruction.registration.scoring import Scorer, scoring_shape

# Pose uncertainty: the objective drop that counts as "indistinguishable" (about the objective's
# change for a one-pixel contour shift at REFINE_PX), the probe step (rad / model radii) and the
# cap for a direction the silhouettes do not constrain.
UNCERTAINTY_DROP = 0.005
UNCERTAINTY_PROBE = 0.01
UNCERTAINTY_MAX = 0.5


def perturb(sim3: Sim3, params: np.ndarray, center: np.ndarray, radius: float) -> Sim3:
    """Sim(3) moved by 7 params (rotation vector, translation in model radii, log-scale) about the model centre, in the object frame."""
    rot = axis_angle_to_matrix(params[:3])
    s = float(np.exp(params[6]))
    delta = Sim3(s, rot, center + radius * params[3:6] - s * rot @ center)
    return delta @ sim3


def refine(
    scorer: Scorer,
    verts: np.ndarray,
    faces: np.ndarray,
    sim3: Sim3,
    center: np.ndarray,
    radius: float,
    *,
    max_evals: int = 200,
    fix_scale: bool = False,
    band: tuple[float, float] = SCALE_SEARCH,
    basis: np.ndarray | None = None,
    steps: np.ndarray | None = None,
    winding: int = 0,
) -> tuple[Sim3, float]:
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
        if not in_band(cand, band):
            return 1.0
        return -float(scorer.scores(verts, faces, cand, winding=winding)[1].mean())

    simplex = np.vstack([np.zeros(n), np.diag(steps)])
    res = minimize(
        cost, np.zeros(n), method="Nelder-Mead", options={"initial_simplex": simplex, "maxfev": max_evals, "xatol": 1e-4, "fatol": 1e-5}
    )
    start = -cost(np.zeros(n))
    if -res.fun < start:
        return sim3, start
    return perturb(sim3, basis @ res.x, center, radius), -float(res.fun)


def pose_sigmas(
    scorer: Scorer, verts: np.ndarray, faces: np.ndarray, sim3: Sim3, center: np.ndarray, radius: float, *, winding: int = 0
) -> np.ndarray:
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


def camera_poses(
    cameras_rig: list[Camera], sim3: Sim3, sigmas: np.ndarray, center: np.ndarray, radius: float, *, samples: int = 64, seed: int = 0
) -> list[dict]:
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
    return [
        {"T_cam_obj": t.tolist(), "rotation_sigma_deg": float(r), "translation_sigma": float(s)}
        for t, r, s in zip(t_cam_obj, rot_sigma, trans_sigma)
    ]


def result_of(
    masks,
    cameras_rig,
    library,
    model: int,
    refined: Sim3,
    objective: float,
    fine: Scorer,
    *,
    alternatives,
    ambiguity,
    model_ties,
    timings,
    t0,
    truncated,
    scale_observable,
    rig_metres_per_unit,
    band,
    method: str = "library_search",
) -> RegistrationResult:
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
        method=method,
    )

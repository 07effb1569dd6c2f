"""The known part (a line running one part): no library search.

The previous part's pose is the prior; the search is the part's yaw about the conveyor normal and its
position (the masks' centroids triangulated), then a local refinement.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from calibration.camera import Camera
from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix
from reconstruction.library import Library
from reconstruction.registration.hypotheses import touches_border
from reconstruction.registration.refine import refine, result_of
from reconstruction.registration.result import RegistrationError, RegistrationResult
from reconstruction.registration.scale import SCALE_TOLERANCE, scale_band
from reconstruction.registration.scoring import Scorer, scoring_shape
from reconstruction.registration.search import check_inputs, register

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
    images: np.ndarray | None = None,
) -> RegistrationResult:
    """The known part again: no library search; the object lies on the conveyor as the previous one did.

    The search space is the part's pose on the conveyor: its yaw about the conveyor normal
    `up_rig` [3] (default: `rig_up`), KNOWN_YAWS of them, and its position (the masks' centroids
    triangulated); the previous part's rig-to-object Sim(3) `prior` gives its resting face and
    scale. The best few yaws are refined in yaw and position, the winner in full pose. Without a
    prior this is a full search restricted to `model_id` (`images` [V, H, W, 3], when given, break
    its near-ties as in `register`).
    """
    t0 = time.perf_counter()
    masks = check_inputs(masks, cameras_rig)
    index = library.index
    if model_id not in index.model_ids:
        raise RegistrationError(f"the known part {model_id!r} is not in the library")
    if prior is None:
        res = register(
            masks,
            cameras_rig,
            library,
            model_ids=[model_id],
            rig_metres_per_unit=rig_metres_per_unit,
            scale_tolerance=scale_tolerance,
            seed=seed,
            images=images,
        )
        return dataclasses.replace(res, method="known_part")
    band = scale_band(rig_metres_per_unit, scale_tolerance)
    return _conveyor_register(masks, cameras_rig, library, model_id, prior, band, up_rig, rig_metres_per_unit, t0)


def _conveyor_register(
    masks: np.ndarray,
    cameras_rig: list[Camera],
    library: Library,
    model_id: str,
    prior: Sim3,
    band: tuple[float, float],
    up_rig: np.ndarray | None,
    rig_metres_per_unit: float | None,
    t0: float,
) -> RegistrationResult:
    """`known_part_register` with a prior: masks [V, H, W] of the part `model_id` resting as `prior` did,
    turned about the conveyor normal `up_rig` [3] (None: `rig_up`) and moved; `t0`, when the registration started."""
    index = library.index
    model = index.model_ids.index(model_id)
    verts, faces, winding = scoring_shape(library, model_id)
    up = rig_up(cameras_rig) if up_rig is None else np.asarray(up_rig, np.float64) / np.linalg.norm(up_rig)
    base, p_prev, p_now = _placement(masks, cameras_rig, verts, faces, prior, band)
    timings = {"observe": time.perf_counter() - t0}

    t = time.perf_counter()
    scorer = Scorer(masks, cameras_rig, KNOWN_SCORE_PX)
    cands = _yaw_candidates(scorer, verts, faces, winding, base, up, p_prev, p_now)
    timings["yaw_search"] = time.perf_counter() - t

    t = time.perf_counter()
    center, radius = index.centers[model], float(index.radii[model])
    best = _refine_on_conveyor(scorer, verts, faces, winding, cands, up, center, radius, band)
    fine = Scorer(masks, cameras_rig, KNOWN_FINAL_PX)
    fix_scale = rig_metres_per_unit is None
    refined, score = refine(
        fine, verts, faces, best[1], center, radius, max_evals=KNOWN_FINAL_EVALS, fix_scale=fix_scale, band=band, winding=winding
    )
    timings["refine"] = time.perf_counter() - t
    return result_of(
        masks,
        cameras_rig,
        library,
        model,
        refined,
        score,
        fine,
        alternatives=[],
        ambiguity=None,
        model_ties=[],
        timings=timings,
        t0=t0,
        truncated=[i for i, m in enumerate(masks) if m.any() and touches_border(m)],
        scale_observable=True,
        rig_metres_per_unit=rig_metres_per_unit,
        band=band,
        method="known_part_prior",
    )


def _placement(
    masks: np.ndarray, cameras_rig: list[Camera], verts: np.ndarray, faces: np.ndarray, prior: Sim3, band: tuple[float, float]
) -> tuple[Sim3, np.ndarray, np.ndarray]:
    """Where the previous part lay and where this one lies: `base`, the prior's rig-to-object Sim(3) at
    its scale clipped to `band` and moved so that the model's area centroid (of `verts` [N, 3], `faces`
    [F, 3]) stays where it is in the object frame; `p_prev` [3], that centroid in the rig frame under the
    prior; `p_now` [3], where masks [V, H, W] put it (triangulated; `p_prev` when they cannot)."""
    s = float(np.clip(prior.scale, *band))
    ref = area_centroid(verts, faces)
    p_prev = prior.inverse().apply(ref[None])[0]
    p_now = triangulate_centroid(masks, cameras_rig)
    if p_now is None:
        p_now = p_prev
    return Sim3(s, prior.rotation, ref - s * prior.rotation @ p_prev), p_prev, p_now


def _yaw_candidates(
    scorer: Scorer,
    verts: np.ndarray,
    faces: np.ndarray,
    winding: int,
    base: Sim3,
    up: np.ndarray,
    p_prev: np.ndarray,
    p_now: np.ndarray,
) -> list[tuple[float, Sim3]]:
    """(mean objective, rig-to-object Sim(3)) of the part turned by each of KNOWN_YAWS yaws about `up` [3]
    through its triangulated centre `p_now` [3], best first."""
    cands = []
    for yaw in np.arange(KNOWN_YAWS) * (2 * np.pi / KNOWN_YAWS):
        turn = axis_angle_to_matrix(yaw * up)
        # x_rig -> turned back about the triangulated centre onto the previous placement -> object.
        sim = base @ Sim3(1.0, turn.T, p_prev - turn.T @ p_now)
        cands.append((float(scorer.scores(verts, faces, sim, winding=winding)[1].mean()), sim))
    cands.sort(key=lambda c: -c[0])
    return cands


def _refine_on_conveyor(
    scorer: Scorer,
    verts: np.ndarray,
    faces: np.ndarray,
    winding: int,
    cands: list[tuple[float, Sim3]],
    up: np.ndarray,
    center: np.ndarray,
    radius: float,
    band: tuple[float, float],
) -> tuple[float, Sim3]:
    """(objective, Sim(3)) of the best of the top KNOWN_STARTS yaw candidates (best first; a runner-up only
    within KNOWN_START_GAP) after refining each in yaw about `up` [3] and position only."""
    best = None
    for _score, sim in [c for c in cands[:KNOWN_STARTS] if c[0] >= cands[0][0] - KNOWN_START_GAP]:
        # Yaw (about the conveyor normal, seen in the object frame) and position only.
        basis = np.zeros((7, 4))
        basis[:3, 0] = sim.rotation @ up
        basis[3:6, 1:] = np.eye(3)
        sim_r, sc_r = refine(
            scorer,
            verts,
            faces,
            sim,
            center,
            radius,
            max_evals=KNOWN_STAGE_EVALS,
            band=band,
            basis=basis,
            steps=np.array([0.1, 0.05, 0.05, 0.05]),
            winding=winding,
        )
        if best is None or sc_r > best[0]:
            best = (sc_r, sim_r)
    return best

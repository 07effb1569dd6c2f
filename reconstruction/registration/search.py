"""Silhouette consensus registration of a calibrated rig to a CAD library (paper section 3.2).

1. Hypotheses per view from the silhouette index (`hypotheses`).
2. RANSAC over Sim(3): sample two views and one hypothesis of the same model from each; rotation
   and translation from the first, scale from the ratio of inter-camera distances; score by
   rendering the model's silhouette in every view (`scoring`).
3. The best distinct candidates are refined briefly (`refine`); the best pose of each model near the
   top is refined fully, and the best of those wins. Other models that end within AMBIGUOUS_GAP are
   reported as ties.

Hard cases: one view or coincident camera centres (the rig-to-object scale is unobservable from
images: it is the metric unit when known, else 1, and the distance to the object comes from the
mask size against the model size); masks touching the image border (scored, but seeding hypotheses
only while no untruncated view can); near-symmetric objects (the best distinct pose and the score gap
are reported; with images, the pose whose colours agree better across views is preferred, `photo`);
nothing above threshold (RegistrationError naming the best IoU found).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from calibration.camera import Camera
from calibration.sim3 import Sim3
from calibration.so3 import geodesic_angle_deg
from reconstruction.library import Library
from reconstruction.parallel import num_threads, parallel_for
from reconstruction.registration.hypotheses import Hypothesis, Observation, match_views, observe, sim3_from_pair
from reconstruction.registration.photo import break_tie
from reconstruction.registration.refine import refine, result_of
from reconstruction.registration.result import RegistrationError, RegistrationResult
from reconstruction.registration.scale import SCALE_TOLERANCE, scale_band
from reconstruction.registration.scoring import REFINE_PX, SCORE_PX, Scorer, cut_short, scoring_shape
from reconstruction.silhouette_index import SilhouetteIndex

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


def check_inputs(masks: np.ndarray, cameras_rig: list[Camera]) -> np.ndarray:
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


@dataclass
class _Search:
    """What the stages of one library search share: the inputs, the scale band and the scoring meshes loaded so far."""

    masks: np.ndarray
    cameras: list[Camera]
    library: Library
    band: tuple[float, float]
    expected: float | None  # a metric rig's scale; None: unknown
    fix_scale: bool
    refine_evals: int
    meshes: dict[int, tuple[np.ndarray, np.ndarray, int]] = field(default_factory=dict)

    @property
    def index(self):
        return self.library.index

    def mesh(self, model: int) -> tuple[np.ndarray, np.ndarray, int]:
        if model not in self.meshes:
            self.meshes[model] = scoring_shape(self.library, self.index.model_ids[model])
        return self.meshes[model]

    def refine(self, scorer: Scorer, model: int, sim: Sim3, max_evals: int) -> tuple[Sim3, float]:
        v_, f_, w_ = self.mesh(model)
        return refine(
            scorer,
            v_,
            f_,
            sim,
            self.index.centers[model],
            float(self.index.radii[model]),
            max_evals=max_evals,
            fix_scale=self.fix_scale,
            band=self.band,
            winding=w_,
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
    masks = check_inputs(masks, cameras_rig)
    band = scale_band(rig_metres_per_unit, scale_tolerance)
    index = library.index
    model_mask = _model_mask(index.model_ids, model_ids)
    rng = np.random.default_rng(seed)
    timings = {}

    observations = [observe(m, c, index.grid.canvas) for m, c in zip(masks, cameras_rig)]
    truncated = [i for i, o in enumerate(observations) if o is not None and o.truncated]
    timings["observe"] = time.perf_counter() - t0
    t = time.perf_counter()
    hyps = _hypotheses(observations, index, top_k, iou_threshold, model_mask)
    timings["match"] = time.perf_counter() - t
    seeds = _seed_views(hyps, truncated)
    centers, spread, scale_observable = _camera_spread(cameras_rig)
    # A metric rig's scale is known up to the part's tolerance; without baselines and units it is set to 1.
    expected = None if rig_metres_per_unit is None else float(rig_metres_per_unit)
    search = _Search(masks, cameras_rig, library, band, expected, fix_scale=not scale_observable, refine_evals=refine_evals)

    t = time.perf_counter()
    scorer = Scorer(masks, cameras_rig, SCORE_PX)
    scored = _scored_candidates(search, scorer, hyps, seeds, centers, spread, rng, iterations, top_k, paired=scale_observable)
    timings["ransac"] = time.perf_counter() - t

    t = time.perf_counter()
    fine = Scorer(masks, cameras_rig, REFINE_PX)
    shortlist, contenders = _decide(search, scorer, fine, scored)
    (score, best_model, refined) = contenders[0]
    model_ties = _model_ties(index, contenders)
    refined, score, ambiguity = _symmetry(search, fine, best_model, refined, score, shortlist + scored, images)
    timings["refine"] = time.perf_counter() - t
    return result_of(
        masks,
        cameras_rig,
        library,
        best_model,
        refined,
        score,
        fine,
        alternatives=_alternatives(index, scored, best_model),
        ambiguity=ambiguity,
        model_ties=model_ties,
        timings=timings,
        t0=t0,
        truncated=truncated,
        scale_observable=scale_observable,
        rig_metres_per_unit=rig_metres_per_unit,
        band=band,
    )


def _hypotheses(
    observations: list[Observation | None], index: SilhouetteIndex, top_k: int, iou_threshold: float, model_mask: np.ndarray | None
) -> list[list[Hypothesis]]:
    """The hypotheses of each view (`match_views`); RegistrationError naming the best IoU found when no view has one."""
    hyps, best_seen = match_views(observations, index, top_k=top_k, iou_threshold=iou_threshold, model_mask=model_mask)
    if not any(hyps):
        raise RegistrationError(
            f"no library silhouette reaches IoU {iou_threshold:.2f} with any mask; the best IoU found was {best_seen:.2f}"
        )
    return hyps


def _seed_views(hyps: list[list[Hypothesis]], truncated: list[int]) -> list[int]:
    """The views whose hypotheses seed RANSAC draws. Truncated silhouettes have a wrong bbox: they seed
    hypotheses only when nothing else can."""
    return [v for v, h in enumerate(hyps) if h and v not in truncated] or [v for v, h in enumerate(hyps) if h]


def _camera_spread(cameras_rig: list[Camera]) -> tuple[np.ndarray, float, bool]:
    """The camera centres [V, 3], their spread (the largest distance from their mean, rig units) and whether
    the rig-to-object scale is observable from them (some baseline between distinct centres)."""
    centers = np.array([c.center for c in cameras_rig])
    spread = float(np.linalg.norm(centers - centers.mean(0), axis=1).max()) if len(centers) > 1 else 0.0
    return centers, spread, spread > 1e-9 * max(1.0, float(np.abs(centers).max()))


def _scored_candidates(
    search: _Search,
    scorer: Scorer,
    hyps: list[list[Hypothesis]],
    seeds: list[int],
    centers: np.ndarray,
    spread: float,
    rng: np.random.Generator,
    iterations: int,
    top_k: int,
    *,
    paired: bool,
) -> list[tuple[float, int, Sim3]]:
    """(mean objective, model, Sim(3)) of the RANSAC candidates (`_ransac`) on `scorer`, best first; of every
    seed hypothesis alone when no draw gave one (each model hypothesised in one view only)."""
    candidates = _ransac(search, hyps, seeds, centers, spread, rng, iterations, paired=paired)
    scored = _score_candidates(scorer, candidates, search.mesh)
    if not scored:
        scored = _single_view_scores(search, scorer, hyps, seeds, top_k)
    scored.sort(key=lambda s: -s[0])
    return scored


def _model_mask(model_ids: list[str], wanted: list[str] | None) -> np.ndarray | None:
    """bool [M]: the library models the search may use (None: all)."""
    if wanted is None:
        return None
    keep = set(wanted)
    mask = np.array([m in keep for m in model_ids])
    if not mask.any():
        raise RegistrationError(f"none of the requested models ({', '.join(sorted(keep))}) is in the library")
    return mask


def _ransac(
    search: _Search,
    hyps: list[list[Hypothesis]],
    seeds: list[int],
    centers: np.ndarray,
    spread: float,
    rng: np.random.Generator,
    iterations: int,
    *,
    paired: bool = True,
) -> list[tuple[int, Sim3]]:
    """(model, Sim(3)) candidates from `iterations` random draws: a seed view's hypothesis, and with `paired` (the scale is
    observable) a hypothesis of the same model in another view at a distinct camera centre for the scale. Repeated draws are skipped."""
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
        if paired:
            partners = [
                v
                for v in range(len(hyps))
                if v != vi and (hi.model, v) in by_model_view and np.linalg.norm(centers[v] - centers[vi]) > 1e-9 * max(1.0, spread)
            ]
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
        candidates += [
            (hi.model, sim)
            for sim in sim3_from_pair(
                hi, second, search.cameras, search.index.centers[hi.model], band=search.band, expected_scale=search.expected
            )
        ]
    return candidates


def _single_view_scores(
    search: _Search, scorer: Scorer, hyps: list[list[Hypothesis]], seeds: list[int], top_k: int
) -> list[tuple[float, int, Sim3]]:
    """Every hypothesising model appears in one view only: no pair to take a scale from, so each seed hypothesis alone."""
    scored = []
    for vi in seeds:
        for h in hyps[vi][:top_k]:
            sim = sim3_from_pair(h, None, search.cameras, search.index.centers[h.model], band=search.band, expected_scale=search.expected)[
                0
            ]
            v_, f_, w_ = search.mesh(h.model)
            scored.append((float(scorer.scores(v_, f_, sim, winding=w_)[1].mean()), h.model, sim))
    return scored


def _decide(search: _Search, scorer: Scorer, fine: Scorer, scored: list[tuple[float, int, Sim3]]):
    """The shortlist (the best CANDIDATES distinct candidates, briefly refined) and the contenders (the best pose of each
    model near the top, fully refined on `fine`), each best first.

    A discrete grid lets a near-symmetric wrong pose outscore the right one before refinement, so the best few distinct
    candidates are refined briefly and the best after that wins. A look-alike (another model that fits as well) is then
    either the winner or reported as a tie, not lost to a brief refinement.
    """
    shortlist: list[tuple[float, int, Sim3]] = []
    for _score, m, sim in scored:
        if len(shortlist) == CANDIDATES:
            break
        if all(m != o[1] or geodesic_angle_deg(sim.rotation, o[2].rotation) > DISTINCT_DEG for o in shortlist):
            sim_r, sc_r = search.refine(scorer, m, sim, search.refine_evals // 4)
            shortlist.append((sc_r, m, sim_r))
    shortlist.sort(key=lambda s: -s[0])
    contenders: list[tuple[float, int, Sim3]] = []
    for sc, m, sim in shortlist:
        if sc >= shortlist[0][0] - TIE_SCREEN and all(m != c[1] for c in contenders) and len(contenders) < CONTENDERS:
            sim_r, sc_r = search.refine(fine, m, sim, search.refine_evals)
            contenders.append((sc_r, m, sim_r))
    contenders.sort(key=lambda c: -c[0])
    return shortlist, contenders


def _model_ties(index, contenders: list[tuple[float, int, Sim3]]) -> list[dict]:
    """Other models whose refined objective is within AMBIGUOUS_GAP of the winner's. cad_size_ratio: the tied model's size
    over the winner's; scale_ratio: the rig-to-object scale it fits at over the winner's. Both equal: the same shape at
    another size, which only a metric rig tells apart."""
    score, best_model, refined = contenders[0]
    return [
        {
            "model_id": index.model_ids[m],
            "score_gap": float(score - sc),
            "cad_size_ratio": float(index.radii[m] / index.radii[best_model]),
            "scale_ratio": float(sim.scale / refined.scale),
        }
        for sc, m, sim in contenders[1:]
        if score - sc < AMBIGUOUS_GAP
    ]


def _symmetry(
    search: _Search, fine: Scorer, model: int, refined: Sim3, score: float, ranked: list[tuple[float, int, Sim3]], images: np.ndarray | None
) -> tuple[Sim3, float, dict | None]:
    """The winner (pose and objective) after the symmetry check, and its report: the best pose of the same `model` in
    `ranked` that is not the same pose is refined; the better of the two wins, and on a near-tie the `images` decide
    (`photo.break_tie`). None: no distinct pose of that model was found."""
    alt = next((s for s in ranked if s[1] == model and geodesic_angle_deg(s[2].rotation, refined.rotation) > DISTINCT_DEG), None)
    if alt is None:
        return refined, score, None
    alt_sim, alt_score = search.refine(fine, model, alt[2], search.refine_evals // 2)
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
        verts, faces, _ = search.mesh(model)
        refined, score = break_tie(images, search.cameras, verts, faces, refined, score, alt_sim, alt_score, ambiguity)
    return refined, score, ambiguity


def _alternatives(index, scored: list[tuple[float, int, Sim3]], best_model: int) -> list[tuple[str, float]]:
    """The other models' best RANSAC scores, best first (at most five)."""
    per_model: dict[int, float] = {}
    for s, m, _ in scored:
        if m != best_model and s > per_model.get(m, -1.0):
            per_model[m] = s
    return [(index.model_ids[m], float(s)) for m, s in sorted(per_model.items(), key=lambda kv: -kv[1])[:5]]

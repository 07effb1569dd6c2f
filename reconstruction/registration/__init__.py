"""Silhouette consensus registration of a calibrated rig to a CAD library (paper section 3.2).

One entry, `register_views(views, library, config)`, used by the `register` command, the service, the
kiosk and `reconstruct`. The package by concern:

- `result`: `RegistrationResult`, its document (`to_dict` / `from_dict`), `provenance`, `check_fits`
- `config`: `RegistrationConfig` (rig.toml's `[registration]`), the one copy of its defaults
- `scale`: the scale band on a metric rig and at unknown scale
- `hypotheses`: masks -> per-view pose hypotheses -> Sim(3) candidates
- `scoring`: the numba silhouette kernels and `Scorer`
- `refine`: local refinement, the pose per camera and its uncertainty
- `photo`: the photographs' near-tie break
- `search`: the library search (`register`); `known_part`: the known part (`known_part_register`)
- `entry`: `register_views`

Evidence for the constants: benchmarks/results/registration*.md.
"""

from reconstruction.registration.config import RegistrationConfig
from reconstruction.registration.entry import register_views, registration_document
from reconstruction.registration.hypotheses import (
    Hypothesis,
    Observation,
    hypothesis,
    independent_poses,
    match_views,
    observe,
    sim3_from_pair,
    touches_border,
)
from reconstruction.registration.known_part import area_centroid, known_part_register, rig_up, triangulate_centroid
from reconstruction.registration.photo import bilinear, break_tie, photo_disagreement
from reconstruction.registration.refine import camera_poses, perturb, pose_sigmas, refine
from reconstruction.registration.result import METHODS, SCALE_SEARCH, RegistrationError, RegistrationResult, check_fits, provenance
from reconstruction.registration.scale import SCALE_TOLERANCE, scale_band
from reconstruction.registration.scoring import REFINE_PX, SCORE_PX, Scorer, boundary, cut_short, scoring_shape
from reconstruction.registration.search import register

__all__ = [
    "METHODS",
    "REFINE_PX",
    "SCALE_SEARCH",
    "SCALE_TOLERANCE",
    "SCORE_PX",
    "Hypothesis",
    "Observation",
    "RegistrationConfig",
    "RegistrationError",
    "RegistrationResult",
    "Scorer",
    "area_centroid",
    "bilinear",
    "boundary",
    "break_tie",
    "camera_poses",
    "check_fits",
    "cut_short",
    "hypothesis",
    "independent_poses",
    "known_part_register",
    "match_views",
    "observe",
    "perturb",
    "photo_disagreement",
    "pose_sigmas",
    "provenance",
    "refine",
    "register",
    "register_views",
    "registration_document",
    "rig_up",
    "scale_band",
    "scoring_shape",
    "sim3_from_pair",
    "touches_border",
    "triangulate_centroid",
]

"""The reconstruction configuration as data: presets `paper` (the paper's table), `cpu` (sized from the scene), `preview`.

"Model only what a scene needs": `resolve_config` reads what the capture says (its `SceneStats`, the
calibration's provenance and metric scale, the initialisation) and returns one `Preset`, every value
the training takes included (the pose mode, the learning-rate table per parameter group and stage).
Nothing is patched after it: an ablation or a caller's override is an input of the resolution too.
`reasons` says why each value is what it is, generated from the resolved configuration; twin.json
stores both. The measurements behind each choice are in docs/presets.md.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

import numpy as np

from reconstruction.deformation import FieldConfig
from reconstruction.gaussians import EPS2D_3DGS
from reconstruction.pose_correction import POSE_MODES

STAGES = ("pose", "deform", "photo")  # Stage I pose only, Stage I pose + deformation, Stage II photometric
INITS = ("cad", "sphere")

# Smoothness weight of the splats' own normal moves (cpu preset; docs/presets.md#displacement).
LAMBDA_DISPLACEMENT = 100.0
# Screen-space variance (px^2) the cpu preset adds to every splat: about a pixel's own footprint, 1/12 px^2 per axis
# (docs/presets.md#eps2d).
EPS2D_PIXEL = 0.1
# The pose + deformation stage's cap from a sphere, in units of the preset's (CAD) cap: the field carves the whole
# shape, not a CAD model's few-% misfit (docs/presets.md#sphere).
SPHERE_DEFORM_FACTOR = 4
# Above this per-camera error of the rig's extrinsics (px at the object), one global Sim(3) leaves every view
# misaligned by more than a pixel: each camera gets its own correction (docs/presets.md#pose-mode).
PER_CAMERA_ABOVE_PX = 1.0
ROUGH_POSE_SOURCES = ("rough", "approximate", "estimated", "phone")


@dataclass(frozen=True)
class StageRates:
    """One parameter group's Adam learning rate at the start of each stage (pose groups decay within a stage)."""

    pose: float
    deform: float
    photo: float

    @staticmethod
    def constant(rate: float) -> StageRates:
        return StageRates(rate, rate, rate)

    def at(self, stage: str) -> float:
        return getattr(self, stage)


@dataclass(frozen=True)
class LearningRates:
    """The learning-rate table: one row per parameter group, one column per stage. A group learns in a stage
    only where the stage trains it (`train.STAGE_PLANS`); a rate of 0 there holds it."""

    pose: StageRates  # the rig's Sim(3) correction
    pose_camera: StageRates  # per-camera SE(3) residuals (per_camera mode)
    deformation: StageRates
    displacement: StageRates  # each splat's own move along its CAD normal
    scales: StageRates
    opacities: StageRates
    sh0: StageRates
    shN: StageRates

    def at(self, group: str, stage: str) -> float:
        return getattr(self, group).at(stage)

    def with_rows(self, rows: Mapping[str, Any]) -> LearningRates:
        """This table with rows replaced: group -> a rate for every stage, or {stage: rate} for some."""
        unknown = sorted(set(rows) - {f.name for f in fields(self)})
        if unknown:
            raise ValueError(f"unknown learning-rate group {unknown[0]!r}; choose from {', '.join(f.name for f in fields(self))}")
        new = {}
        for group, row in rows.items():
            if isinstance(row, Mapping):
                bad = sorted(set(row) - set(STAGES))
                if bad:
                    raise ValueError(f"unknown stage {bad[0]!r} in the learning rates of {group!r}; choose from {', '.join(STAGES)}")
                new[group] = replace(getattr(self, group), **{s: float(v) for s, v in row.items()})
            else:
                new[group] = StageRates.constant(float(row))
        return replace(self, **new)

    @staticmethod
    def from_dict(doc: Mapping[str, Mapping[str, float]]) -> LearningRates:
        return LearningRates(**{f.name: StageRates(**doc[f.name]) for f in fields(LearningRates)})


PAPER_RATES = LearningRates(
    pose=StageRates.constant(5e-4),
    pose_camera=StageRates.constant(5e-4),
    deformation=StageRates.constant(1.6e-5),
    displacement=StageRates.constant(0.0),
    scales=StageRates.constant(5e-3),
    opacities=StageRates.constant(5e-2),
    sh0=StageRates.constant(2.5e-3),
    shN=StageRates.constant(1.25e-4),
)


@dataclass(frozen=True)
class Preset:
    """One resolved configuration: everything `train` and `reconstruct` take, and nothing else."""

    name: str
    num_splats: int
    sh_degree: int
    field: FieldConfig
    iters_pose: int  # Stage I, pose only
    iters_deform: int  # Stage I, pose + deformation
    iters_photo: int  # Stage II
    plateau: bool = False  # stop a stage early once its loss stops falling
    dropout_p0: float = 0.5
    dropout_anneal: int = 20_000  # Stage-II iterations over which dropout goes to 0
    sh_neighbours: int = 20
    lambda_dssim: float = 0.2
    lambda_mask: float = 1.0
    lambda_sh: float = 1.0
    pose_scale: bool = True  # the global pose correction learns its log-scale (else the registration's scale stays)
    lambda_fill: float = 0.0  # Stage II: weight of L_fill in `losses.silhouette_losses` (alpha saturation inside the mask); 0 is the paper
    lambda_displacement: float = 0.0  # weight of the neighbour smoothness of the splats' own normal moves
    lambda_consistency: float = 0.0  # Stage I: weight of multi-view photo-consistency (`photo_consistency`); 0 is the paper
    consistency_blur_px: float = 1.0  # Gaussian blur of the images it samples (reach of its gradients)
    lr: LearningRates = PAPER_RATES
    refine_steps: int = 400
    image_scale: float = 1.0  # Stage-II training resolution relative to the capture
    mask_scale: float = 1.0  # Stage-I (silhouette) resolution relative to the capture
    checkpoint_every: int = 500
    views_per_iter: int = 1  # training views rendered per iteration (the paper, as 3DGS: one); 0: all
    init_opacity: float = 0.5
    pose_lr_final: float = 1.0  # pose learning rate at a stage's end relative to its start (exponential decay)
    eps2d: float = EPS2D_3DGS  # screen-space variance (px^2) added to every splat in training and in the twin's renders
    shn_decay: float = 0.0  # Stage II: decoupled weight decay of the higher SH bands (per unit of their rate)
    max_scale_growth: float | None = None  # each splat's scales are clamped to this multiple of its initial largest one (None: unbounded)
    max_normal_growth: float | None = (
        None  # each disk's normal axis (its thickness) is clamped to this multiple of its start (None: only max_scale_growth)
    )
    pose_mode: str = "global"  # "global": one Sim(3) for the rig; "per_camera": plus an SE(3) residual per camera
    plateau_rel_tol: tuple[float, float, float] = (0.01, 0.01, 0.003)  # per stage: the relative gain under which a window plateaus
    plateau_window: tuple[int, int] = (20, 12)  # (fewest iterations, windows per stage cap): single-view losses are noisy
    adam_eps: float = 1e-15

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(doc: Mapping[str, Any]) -> Preset:
        """The configuration `to_dict` wrote (twin.json `config`); a field this engine does not know is refused in one sentence."""
        unknown = sorted(set(doc) - {f.name for f in fields(Preset)})
        if unknown:
            raise ValueError(f"the recorded configuration has a field this engine does not know ({unknown[0]!r})")
        return Preset(
            **{
                **doc,
                "field": FieldConfig(**doc["field"]),
                "lr": LearningRates.from_dict(doc["lr"]),
                "plateau_rel_tol": tuple(doc["plateau_rel_tol"]),
                "plateau_window": tuple(doc["plateau_window"]),
            }
        )


PAPER = Preset(
    name="paper",
    num_splats=600_000,
    sh_degree=3,
    field=FieldConfig(8, 256, 10, None),
    iters_pose=3000,
    iters_deform=3000,
    iters_photo=24_000,
)


@dataclass(frozen=True)
class SceneStats:
    """What the cpu preset sizes itself from: per-view foreground pixels, image size, camera geometry."""

    num_views: int
    width: int
    height: int
    foreground_px: tuple[int, ...]
    coverage_deg: float  # largest angle between two viewing directions towards the object

    @property
    def total_foreground_px(self) -> int:
        return int(sum(self.foreground_px))


def scene_stats(masks: np.ndarray, c2w: np.ndarray, target: np.ndarray) -> SceneStats:
    """masks [V, H, W] bool, camera-to-object poses c2w [V, 4, 4], object centre `target` [3]."""
    dirs = np.asarray(target, np.float64) - c2w[:, :3, 3]
    dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-12)
    cos = np.clip(dirs @ dirs.T, -1, 1)
    coverage = float(np.degrees(np.arccos(cos.min()))) if len(dirs) > 1 else 0.0
    v, h, w = masks.shape
    return SceneStats(v, w, h, tuple(int(m.sum()) for m in masks), coverage)


@dataclass(frozen=True)
class ConfigInputs:
    """Everything a configuration is resolved from, beside the preset's name.

    metric: the rig frame has a calibration's metric scale (then the field keeps uniform scaling).
    pose_source / calibration_id: the capture's stated provenance of its poses (`capture.meta`).
    calibration_error_px: the calibration's stated extrinsic uncertainty in pixels at the object, when stated.
    pose_mode: the caller's choice of pose mode (None: chosen from the provenance).
    ablations: names of `ABLATIONS`; overrides: `Preset` fields set by the caller (nested `field`/`lr` merge).
    """

    stats: SceneStats
    metric: bool = True
    init: str = "cad"
    pose_source: str | None = None
    calibration_id: str | None = None
    calibration_error_px: float | None = None
    pose_mode: str | None = None
    ablations: tuple[str, ...] = ()
    overrides: Mapping[str, Any] = field(default_factory=dict)

    @property
    def rough_poses(self) -> bool:
        """Whether the provenance marks the poses as rough (degrees off, not a calibration)."""
        return str(self.pose_source or "").lower() in ROUGH_POSE_SOURCES

    @property
    def coarse_poses(self) -> bool:
        """Rough poses, or a calibration stated to be off by more than `PER_CAMERA_ABOVE_PX` at the object."""
        return self.rough_poses or (self.calibration_error_px or 0.0) > PER_CAMERA_ABOVE_PX


def sh_degree_for(stats: SceneStats) -> int:
    """View-dependent colour needs views from several directions to be constrained at all."""
    if stats.num_views < 4 or stats.coverage_deg < 30:
        return 0
    return 1 if stats.num_views < 8 or stats.coverage_deg < 90 else 2


def training_scale(stats: SceneStats, preview: bool) -> float:
    """Stages I and II train at capture size up to 384 px on the long side (240 for preview; docs/presets.md#image-scale)."""
    return min(1.0, (240 if preview else 384) / max(stats.width, stats.height))


def splat_budget(stats: SceneStats, preview: bool) -> tuple[float, int, int]:
    """(splats per foreground pixel at training scale, cap, floor)."""
    return (0.5, 8_000, 2_000) if preview else (0.5, 15_000, 4_000)


def sized_rates(preview: bool) -> LearningRates:
    """The sized presets' rates: the slow groups faster than the paper's for ~100x fewer iterations, Stage II's full-batch
    colours faster still, the rig's pose frozen in Stage II, per-camera residuals fine from the second Stage-I stage on
    (docs/presets.md#learning-rates)."""
    pose = 2e-3
    return LearningRates(
        pose=StageRates(pose, pose, 0.0),
        pose_camera=StageRates(0.0, 3e-5, 3e-5),
        deformation=StageRates.constant(2e-4 if preview else 1e-4),
        displacement=StageRates.constant(0.0 if preview else 1e-3),
        scales=StageRates.constant(1e-2),
        opacities=StageRates.constant(2e-2),
        sh0=StageRates.constant(4e-2),
        shN=StageRates.constant(4e-3),
    )


def resolve_preset(name: str, stats: SceneStats) -> Preset:
    """The preset named `name` sized for the scene (before the capture's provenance, the init and the caller's word)."""
    if name == "paper":
        return PAPER
    if name not in ("cpu", "preview"):
        raise ValueError(f"unknown preset {name!r}; choose cpu, preview or paper")
    preview = name == "preview"
    scale = training_scale(stats, preview)
    per_px, cap, floor = splat_budget(stats, preview)
    n = int(np.clip(round(per_px * stats.total_foreground_px * scale * scale), floor, cap))
    # Fewer than 5 views leave the finest of the paper's 10 bands unconstrained (docs/presets.md#bands).
    bands = 6 if not preview and stats.num_views < 5 else 10
    # The field carries no rigid motion: the pose does (docs/presets.md#deformation).
    fc = FieldConfig(
        depth=4 if preview else 6,
        width=64 if preview else 128,
        bands=bands,
        num_anchors=int(min(n, 512 if preview else 2048)),
        anchor_k=4,
        project_similarity=True,
    )
    # Stage II: 200 iterations with 8 or more views, 150 with fewer (docs/presets.md#iterations).
    iters = (20, 40, 50) if preview else (60, 100, 200 if stats.num_views >= 8 else 150)
    return Preset(
        name=name,
        num_splats=n,
        sh_degree=0 if preview else sh_degree_for(stats),
        field=fc,
        iters_pose=iters[0],
        iters_deform=iters[1],
        iters_photo=iters[2],
        plateau=not preview,
        dropout_p0=0.0,
        dropout_anneal=0,
        lr=sized_rates(preview),
        # lambda_SH scaled by N / 600k keeps the paper's smoothing per unit of surface (docs/presets.md#lambda-sh).
        lambda_sh=min(1.0, n / PAPER.num_splats),
        refine_steps=50 if preview else 100,
        image_scale=scale,
        mask_scale=scale,
        checkpoint_every=50,
        views_per_iter=0,
        plateau_window=(10, 15),
        init_opacity=0.9,
        pose_lr_final=0.1,
        pose_scale=False,
        lambda_fill=1.5 if preview else 0.0,
        lambda_consistency=1.0,
        consistency_blur_px=1.0,
        lambda_displacement=0.0 if preview else LAMBDA_DISPLACEMENT,
        lambda_dssim=0.6 if preview else 0.2,
        eps2d=EPS2D_3DGS if preview else EPS2D_PIXEL,
        max_scale_growth=2.0,
        max_normal_growth=1.0 if not preview and stats.num_views < 5 else None,
        shn_decay=0.0 if preview else 1.0,
    )


def choose_pose_mode(inputs: ConfigInputs) -> str:
    """The pose mode from the capture's provenance, unless the caller chose one (docs/presets.md#pose-mode)."""
    if inputs.pose_mode is not None:
        if inputs.pose_mode not in POSE_MODES:
            raise ValueError(f"pose mode must be one of {', '.join(POSE_MODES)}, got {inputs.pose_mode!r}")
        return inputs.pose_mode
    if inputs.rough_poses or (inputs.calibration_error_px is not None and inputs.calibration_error_px > PER_CAMERA_ABOVE_PX):
        return "per_camera"
    # Poses of unknown provenance (no calibration named) are not assumed exact: fine per-camera residuals.
    return "global" if inputs.calibration_id else "per_camera"


def resolve_config(name: str, inputs: ConfigInputs) -> Preset:
    """The whole configuration of one reconstruction: the preset sized for the scene, then what the capture's
    provenance, the initialisation, the ablations and the caller's overrides say, in that order."""
    if inputs.init not in INITS:
        raise ValueError(f"unknown init {inputs.init!r}; choose cad or sphere")
    cfg = resolve_preset(name, inputs.stats)
    mode = choose_pose_mode(inputs)
    cfg = replace(cfg, pose_mode=mode)
    if cfg.field.project_similarity:
        cfg = replace(cfg, field=replace(cfg.field, projection_keeps_scale=inputs.metric))
    if inputs.init == "sphere":
        cfg = replace(cfg, iters_deform=SPHERE_DEFORM_FACTOR * cfg.iters_deform)
    if mode == "per_camera" and inputs.coarse_poses:
        # Rough poses have degrees to travel: residuals at the rig's rate in the second Stage-I stage, held in Stage II.
        cfg = replace(cfg, lr=replace(cfg.lr, pose_camera=replace(cfg.lr.pose_camera, deform=cfg.lr.pose.deform, photo=0.0)))
    cfg = apply_ablations(cfg, inputs.ablations)
    return apply_overrides(cfg, inputs.overrides) if inputs.overrides else cfg


def apply_overrides(cfg: Preset, overrides: Mapping[str, Any]) -> Preset:
    """`cfg` with `Preset` fields set by the caller; the deformation field's config and the learning-rate table merge."""
    unknown = sorted(set(overrides) - {f.name for f in fields(Preset)})
    if unknown:
        raise ValueError(f"unknown preset field {unknown[0]!r} in overrides")
    merged = {}
    for key, value in overrides.items():
        if key == "field" and isinstance(value, Mapping):
            value = replace(cfg.field, **value)
        elif key == "lr" and isinstance(value, Mapping):
            value = cfg.lr.with_rows(value)
        merged[key] = value
    return replace(cfg, **merged)


def _no_mask_warmup(p: Preset) -> Preset:
    # Stage I's iterations move to Stage II so the ablated run trains as long as the full one.
    return replace(p, iters_photo=p.iters_photo + p.iters_pose + p.iters_deform, iters_pose=0, iters_deform=0)


def _frozen(p: Preset, *groups: str) -> Preset:
    return replace(p, lr=replace(p.lr, **{g: StageRates.constant(0.0) for g in groups}))


# The paper's ablations (section 4.4.3): each switches one ingredient off and keeps the rest.
ABLATIONS = {
    "no-deformation": (lambda p: replace(_frozen(p, "deformation"), iters_deform=0), "the deformation field stays at identity"),
    "no-pose": (lambda p: replace(_frozen(p, "pose", "pose_camera"), iters_pose=0), "the registration's pose is never corrected"),
    "no-mask-warmup": (_no_mask_warmup, "no Stage I: Stage II starts from the registration and gets Stage I's iterations"),
    "no-sh-smoothness": (lambda p: replace(p, lambda_sh=0.0), "lambda_SH = 0"),
    "no-dropout": (lambda p: replace(p, dropout_p0=0.0), "splat dropout off"),
}


def apply_ablations(preset: Preset, names) -> Preset:
    """`preset` with the named `ABLATIONS` switched off."""
    unknown = [n for n in names if n not in ABLATIONS]
    if unknown:
        raise ValueError(f"unknown ablation {unknown[0]!r}; choose from {', '.join(ABLATIONS)}")
    for n in names:
        preset = ABLATIONS[n][0](preset)
    return preset


def ablation_reason(preset: Preset, names) -> str:
    """What each named ablation does, and whether it changed anything on `preset` (the configuration before them)."""
    whys = []
    for n in names:
        fn, why = ABLATIONS[n]
        after = fn(preset)
        whys.append(f"{n}: {why}" + (" (already off in this preset)" if after == preset else ""))
        preset = after
    return "; ".join(whys)


def _choice(value, why: str) -> dict:
    return {"value": value, "why": why}


def _sizing_reasons(cfg: Preset, stats: SceneStats) -> dict:
    """Why the scene-sized values are what they are (read from `cfg`)."""
    long_side = max(stats.width, stats.height)
    per_px, cap, floor = splat_budget(stats, cfg.name == "preview")
    fg = int(stats.total_foreground_px * cfg.image_scale * cfg.image_scale)
    fc = cfg.field
    few = f"; {fc.bands} frequency bands: {stats.num_views} views leave finer ones unconstrained" if fc.bands < 10 else ""
    if cfg.name == "preview":
        sh_why = "preview: diffuse colour only"
    else:
        sh_why = {
            0: "cannot constrain view dependence",
            1: "constrain only linear view dependence",
            2: "constrain low-order view dependence; degree 3's 21 more coefficients per splat would be left to the SH regulariser",
        }[cfg.sh_degree]
        sh_why = f"{stats.num_views} views spanning {stats.coverage_deg:.0f} deg {sh_why}"
    return {
        "image_scale": _choice(
            round(cfg.image_scale, 4),
            f"Stage II renders {long_side} px images at <= {round(cfg.image_scale * long_side)} px on the long side",
        ),
        "mask_scale": _choice(
            round(cfg.mask_scale, 4), f"Stage I silhouettes at <= {round(cfg.mask_scale * long_side)} px on the long side"
        ),
        "num_splats": _choice(
            cfg.num_splats,
            f"{per_px} splat per foreground pixel over {stats.num_views} views at training scale ({fg} px), clipped to [{floor}, {cap}]",
        ),
        "sh_degree": _choice(cfg.sh_degree, sh_why),
        "deformation": _choice(
            asdict(fc),
            f"MLP {fc.depth}x{fc.width} evaluated at {fc.num_anchors} farthest-point anchors and blended to "
            f"the {cfg.num_splats} splats; its rigid (and, without a metric rig, similarity) component "
            f"projected out{few}",
        ),
        "lambda_sh": _choice(
            round(cfg.lambda_sh, 5),
            f"paper's 1.0 scaled by {cfg.num_splats} / 600k splats: the same smoothing per unit "
            f"of surface, over each splat's {cfg.sh_neighbours} nearest less those across a thin wall",
        ),
    }


def _schedule_reasons(cfg: Preset, inputs: ConfigInputs) -> dict:
    """Why the iteration caps and the learning rates are what they are (read from `cfg`)."""
    caps = {"pose": cfg.iters_pose, "deform": cfg.iters_deform, "photo": cfg.iters_photo}
    if cfg.name == "preview":
        why = "fixed short schedule for a first look"
    else:
        why = f"caps; each stage stops earlier once its loss plateaus; Stage II {cfg.iters_photo}: " + (
            "8 or more views keep gaining past 150" if inputs.stats.num_views >= 8 else "fewer than 8 views gain nothing past 150"
        )
    if inputs.init == "sphere":
        why += f"; the pose + deformation stage {SPHERE_DEFORM_FACTOR}x longer from a sphere, which the field must carve into the object"
    rates = (
        "the rig's pose at a rate decaying to "
        f"{cfg.pose_lr_final:g}x over each stage (translation in object radii); the other groups at a constant rate; "
        "0 holds a group in a stage"
    )
    if cfg.pose_mode == "per_camera" and inputs.coarse_poses:
        rates += (
            f"; poses rough or stated to be off by more than {PER_CAMERA_ABOVE_PX:g} px: per-camera residuals at the rig's rate "
            "in the second Stage-I stage, held in Stage II"
        )
    return {"iteration_caps": _choice(caps, why), "learning_rates": _choice(asdict(cfg.lr), rates)}


def _pose_mode_reason(cfg: Preset, inputs: ConfigInputs) -> str:
    px = inputs.calibration_error_px
    if inputs.pose_mode is not None:
        return "set by the caller"
    if inputs.rough_poses:
        return f"capture poses are marked pose_source={inputs.pose_source!r}: each view gets its own SE(3) correction"
    if px is not None and px > PER_CAMERA_ABOVE_PX:
        return (
            f"rig calibration {inputs.calibration_id!r} is good to {px:.1f} px per camera at the object; one global correction "
            f"cannot remove per-camera errors above {PER_CAMERA_ABOVE_PX:g} px, so each view gets its own SE(3) correction"
        )
    if inputs.calibration_id:
        good = f" (good to {px:.2f} px at the object)" if px is not None else ""
        return f"rig calibration {inputs.calibration_id!r}{good}: one global Sim(3) correction for all cameras"
    return (
        "no calibration is named, so its accuracy is unknown: the rig's Sim(3) correction, and per camera a "
        "small SE(3) residual learnt from the photographs"
    )


def _loss_reasons(cfg: Preset) -> dict:
    """Why the losses, the splats' bounds and their dilation are what they are (read from `cfg`)."""
    preview = cfg.name == "preview"
    out = {
        "pose_scale": _choice(
            cfg.pose_scale,
            "the global correction learns rotation and translation; the registration fixes the scale"
            if not cfg.pose_scale
            else "the global correction learns its scale",
        ),
        "lambda_fill": _choice(
            cfg.lambda_fill,
            "alpha pushed to saturate inside the mask so the object's rim renders opaque"
            if cfg.lambda_fill
            else "off: full-size Stage II fits the rim; the fill term spilled past it",
        ),
        "lambda_dssim": _choice(
            cfg.lambda_dssim,
            "preview: SSIM carries more of the short fit's photometric loss"
            if preview
            else "the paper's (3DGS's) share of SSIM in the photometric loss",
        ),
        "eps2d": _choice(
            cfg.eps2d,
            f"preview: 3DGS's {EPS2D_3DGS} px^2; its short fit left smaller splats' silhouettes thin"
            if preview
            else f"each splat drawn {cfg.eps2d} px^2 wider, about a pixel's own footprint (1/12 px^2), in training and "
            f"in every render of the twin; 3DGS's {EPS2D_3DGS} blurred every edge",
        ),
        "max_scale_growth": _choice(
            cfg.max_scale_growth,
            f"a splat's scales stay within {cfg.max_scale_growth:g}x its initial largest one, "
            "the spacing to its nearest splats: larger ones cover what their neighbours own",
        ),
        "max_normal_growth": _choice(
            cfg.max_normal_growth,
            "few views hardly see a disk edge-on: its thickness stays at most where it started"
            if cfg.max_normal_growth is not None
            else "off: the disks' thickness learns up to the scale bound",
        ),
        "shn_decay": _choice(
            cfg.shn_decay,
            "the higher SH bands decay towards no view dependence unless the photographs hold them up" if cfg.shn_decay else "off",
        ),
        "lambda_consistency": _choice(
            cfg.lambda_consistency,
            "Stage I adds multi-view photo-consistency of the surface: silhouettes alone leave the surface inside the outline free",
        ),
        "views_per_iter": _choice(
            "all" if cfg.views_per_iter <= 0 else cfg.views_per_iter,
            "every training view in every iteration: batched views render cheaper and the full-batch loss makes the plateau test exact",
        ),
        "init_opacity": _choice(cfg.init_opacity, "one surface layer near-opaque, so back faces do not bleed through"),
        "dropout": _choice(
            {"p0": cfg.dropout_p0, "anneal_iters": cfg.dropout_anneal},
            "off: it regularises 600k splats over 24k iterations, not a few thousand seen by all views each step",
        ),
    }
    if cfg.lr.displacement.photo:
        out["displacement"] = _choice(
            {"lr": cfg.lr.displacement.photo, "lambda": cfg.lambda_displacement},
            "each splat also moves along its CAD normal (smoothed over its neighbours): the field is too smooth "
            "to follow what the CAD's decimation took away",
        )
    return out


def reasons(cfg: Preset, inputs: ConfigInputs) -> dict:
    """{name: {"value", "why"}} for the resolved configuration `cfg`, each value read from it (twin.json `choices`)."""
    out: dict = {
        "preset": _choice(
            cfg.name,
            "the paper's hyperparameter table, unchanged"
            if cfg.name == "paper"
            else "sized from the capture: "
            + ", ".join(f"{k} {v}" for k, v in (("views", inputs.stats.num_views), ("coverage deg", round(inputs.stats.coverage_deg)))),
        )
    }
    if cfg.name != "paper":
        out.update(_sizing_reasons(cfg, inputs.stats))
        out.update(_schedule_reasons(cfg, inputs))
        out.update(_loss_reasons(cfg))
    elif inputs.init == "sphere":
        out["iteration_caps"] = _schedule_reasons(cfg, inputs)["iteration_caps"]
    out["pose_mode"] = _choice(cfg.pose_mode, _pose_mode_reason(cfg, inputs))
    if inputs.init == "sphere":
        out["init"] = _choice(
            "sphere",
            "paper 4.4.2: no CAD; an icosphere at the optical axes' meeting point, sized so its projections match the masks' areas",
        )
    if inputs.ablations:
        out["ablations"] = _choice(list(inputs.ablations), ablation_reason(_before_ablations(cfg.name, inputs), inputs.ablations))
    if inputs.overrides:
        out["overrides"] = _choice(dict(inputs.overrides), "set by the caller, the last input of the resolution")
    return out


def _before_ablations(name: str, inputs: ConfigInputs) -> Preset:
    return resolve_config(name, replace(inputs, ablations=(), overrides={}))

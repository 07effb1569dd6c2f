"""The two-stage training schedule (paper 3.6) over CAD-anchored splats.

Stage I (geometric warm-up, silhouettes only): L_mask on the rendered alpha; first the pose
correction alone ("pose"), then pose + deformation field ("deform"). Stage II ("photo"): L_rgb on
random-background composites + λ_mask L_mask + λ_SH L_SH, with splat dropout on the RGB render
(the mask render uses every splat); pose, field, scales, opacities and SH all learn, each group
with its own Adam learning rate. Stage II starts from SH DC colours projected from the training
images at the Stage-I poses. Means and quaternions never learn.

The stages are data (`STAGE_PLANS`: trainable groups, loss, plateau rule) over a typed `TrainState`;
each group's rate in each stage is the configuration's table (`presets.LearningRates`), and the pose
groups' rates decay exponentially over a stage to `preset.pose_lr_final` of their start.
`preset.views_per_iter` views per iteration: one random view as 3DGS (the paper), or all of them
(0), which the rasterizer renders cheaper per view and which makes every loss a full-batch value.
Non-finite losses or gradients skip the step (counted, never applied). A checkpoint saved every
`checkpoint_every` iterations and at each stage end (to a `CheckpointStore` the caller provides)
lets an interrupted run resume where it stopped; it holds only tensors and plain values.
"""

from __future__ import annotations

import hashlib
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import NamedTuple, Protocol

import cv2
import numpy as np
import torch
from torch import nn

from reconstruction.adam import Adam
from reconstruction.deformation import DeformationField, idw_weights, normal_similarity_basis
from reconstruction.gaussians import Gaussians, render
from reconstruction.losses import (
    composite,
    composite_parts,
    dropout_active,
    dropout_fraction,
    mask_l1,
    neighbour_graph,
    neighbour_smoothness,
    photometric_loss,
    sh_neighbour_loss,
    silhouette_losses,
)
from reconstruction.photo_consistency import blurred, consistency_loss, sample_colors, visibility_weights
from reconstruction.pose_correction import PoseCorrection, viewmats_from_c2w
from reconstruction.presets import Preset
from reconstruction.render import rasterize
from reconstruction.splats import CanonicalSplats, point_visibility, project_colors, rgb_to_sh_dc, surface_neighbours

ProgressFn = Callable[[str, int, int, float], None]


class ViewBatch(NamedTuple):
    """The training views at one scale: images [V, h, w, 3], mask coverage [V, h, w] in [0, 1], the pixels
    each photograph has `valid` [V, h, w] bool (None when every photo fills the canvas), Ks [V, 3, 3]."""

    images: torch.Tensor
    coverage: torch.Tensor
    valid: torch.Tensor | None
    Ks: torch.Tensor
    width: int
    height: int


@dataclass
class Views:
    """Training views at capture resolution: images [V, H, W, 3] float32, masks [V, H, W] bool,
    Ks [V, 3, 3], camera-to-object poses c2w [V, 4, 4] (float64, OpenCV) from the registration.

    sizes [V, 2] (width, height), optional: each photo's own size, when views of mixed sizes may share
    the canvas top-left (`load_views`); None means every photo fills it.
    """

    images: np.ndarray
    masks: np.ndarray
    Ks: np.ndarray
    c2w: np.ndarray
    sizes: np.ndarray | None = None

    def resized(self, scale: float) -> ViewBatch:
        """The views at `scale`. Area resampling keeps the fraction of each low-res pixel the object
        covers; K scales with the continuous pixel coordinates (pixel edges at integers map onto pixel
        edges). A low-res pixel is valid when all of it lies on its photo."""
        v, h, w = self.masks.shape
        w2, h2 = max(1, round(w * scale)), max(1, round(h * scale))

        def area(stack: np.ndarray) -> np.ndarray:
            if (w2, h2) == (w, h):
                return stack
            return np.stack([cv2.resize(a, (w2, h2), interpolation=cv2.INTER_AREA) for a in stack])

        imgs, cov = area(self.images), area(self.masks.astype(np.float32))
        valid = None
        if self.sizes is not None and np.any(np.asarray(self.sizes) != [w, h]):
            on_photo = np.zeros((v, h, w), np.float32)
            for o, (pw, ph) in zip(on_photo, np.asarray(self.sizes)):
                o[:ph, :pw] = 1.0
            valid = torch.from_numpy(area(on_photo) > 1.0 - 1e-6)
        ks = self.Ks.copy()
        ks[:, 0] *= w2 / w
        ks[:, 1] *= h2 / h
        return ViewBatch(
            torch.tensor(imgs, dtype=torch.float32),
            torch.tensor(cov, dtype=torch.float32),
            valid,
            torch.tensor(ks, dtype=torch.float32),
            w2,
            h2,
        )


class SplatModel(nn.Module):
    """Learnable state: frozen canonical means/quats, deformation field, pose correction, scales,
    opacities and SH (DC and higher bands as separate groups for their learning rates)."""

    def __init__(self, splats: CanonicalSplats, preset: Preset, num_cameras: int, pose_mode: str, seed: int = 0):
        super().__init__()
        g = splats.gaussians
        self.register_buffer("means_canonical", torch.tensor(g.means, dtype=torch.float32))
        self.register_buffer("quats", torch.tensor(g.quats, dtype=torch.float32))
        self.field = DeformationField(splats.means, preset.field, seed=seed)
        # Fine geometry below the field's resolution: each splat moves along its CAD normal (in object radii).
        self.register_buffer("normals_canonical", torch.tensor(splats.normals, dtype=torch.float32))
        self.displacement = nn.Parameter(torch.zeros(len(g.means), dtype=torch.float32))
        self.pose = PoseCorrection(num_cameras, pose_mode, pivot=self.field.center.double().numpy(), unit=float(self.field.radius))
        # Normal moves that amount to a motion of the pose's (rigid, and with pose_scale similarity) would let
        # the splats and the cameras drift together: that component is projected out, as for the field.
        basis = normal_similarity_basis(
            splats.means, splats.normals, self.field.center.double().numpy(), float(self.field.radius), with_scale=preset.pose_scale
        )
        self.register_buffer("displacement_basis", torch.tensor(basis, dtype=torch.float32))
        self.register_buffer("displacement_pinv", torch.tensor(np.linalg.pinv(basis), dtype=torch.float32))
        self.log_scales = nn.Parameter(torch.tensor(g.log_scales, dtype=torch.float32))
        self.opacity_logits = nn.Parameter(torch.tensor(g.opacity_logits, dtype=torch.float32))
        sh = torch.tensor(g.sh, dtype=torch.float32)
        self.sh0 = nn.Parameter(sh[:, :1].clone())
        self.shN = nn.Parameter(sh[:, 1:].clone())
        self.sh_degree = g.sh_degree
        self.eps2d = preset.eps2d
        # Scale bounds relative to the object: no splat collapses to nothing or swallows the object.
        radius = float(self.field.radius)
        self.log_scale_range = (math.log(1e-5 * radius), math.log(0.5 * radius))
        # And relative to the splat's own start, its neighbours' spacing (`preset.max_scale_growth`), and the disk's
        # normal axis (local z, `splats.disk_log_scales`) relative to its own start (`preset.max_normal_growth`):
        # [N, 1], [N, 3] or None.
        start = self.log_scales.detach()
        growth, normal_growth = preset.max_scale_growth, preset.max_normal_growth
        self.log_scale_max = None if growth is None else start.amax(1, keepdim=True) + math.log(growth)
        if normal_growth is not None:
            tangent = self.log_scale_max if growth is not None else torch.full_like(start[:, :1], math.inf)
            normal = torch.minimum(tangent, start[:, 2:] + math.log(normal_growth))
            self.log_scale_max = torch.cat([tangent, tangent, normal], 1)

    def means(self) -> torch.Tensor:
        """Deformed means [N, 3] = μ + D(γ(μ)) + d n: the field, then each splat's move along its normal."""
        return self.means_canonical + self.field() + self.displacement_offsets()

    def normal_moves(self) -> torch.Tensor:
        """[N] each splat's own move along its canonical normal (object radii), without the part a pose could make."""
        return self.displacement - self.displacement_basis @ (self.displacement_pinv @ self.displacement)

    def displacement_offsets(self) -> torch.Tensor:
        """[N, 3] each splat's own move along its canonical normal, metres."""
        return (self.normal_moves() * self.field.radius)[:, None] * self.normals_canonical

    @torch.no_grad()
    def offsets_at(self, points: np.ndarray, k: int = 4) -> np.ndarray:
        """Δ [P, 3] at canonical points (e.g. CAD vertices): the field there plus the inverse-distance blend
        of the k nearest splats' own moves, so a mesh through them follows the splats."""
        idx, w = idw_weights(np.asarray(points, np.float64), self.means_canonical.numpy().astype(np.float64), k)
        return self.field.offsets_at(points) + np.einsum("nk,nkd->nd", w, self.displacement_offsets().numpy()[idx])

    def sh(self) -> torch.Tensor:
        return torch.cat([self.sh0, self.shN], 1)

    def gaussians(self) -> Gaussians:
        """The current Gaussians (object frame) as tensors that carry the training graph."""
        return Gaussians(self.means(), self.quats, self.log_scales, self.opacity_logits, self.sh(), self.eps2d)

    def viewmats(self, c2w_init: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """World-to-camera [C, 4, 4] float32 of cameras `index` after the pose correction."""
        corrected = self.pose(c2w_init[index], index)
        return viewmats_from_c2w(corrected).to(torch.float32)

    def param_groups(self) -> list[dict]:
        """The parameter groups, named as the rows of `presets.LearningRates` (their rates are set per stage)."""
        camera = self.pose.camera_parameters()
        return [
            {"name": "pose", "params": self.pose.rig_parameters(), "lr": 0.0},
            *([{"name": "pose_camera", "params": camera, "lr": 0.0}] if camera else []),
            {"name": "deformation", "params": list(self.field.parameters()), "lr": 0.0},
            {"name": "displacement", "params": [self.displacement], "lr": 0.0},
            {"name": "scales", "params": [self.log_scales], "lr": 0.0},
            {"name": "opacities", "params": [self.opacity_logits], "lr": 0.0},
            {"name": "sh0", "params": [self.sh0], "lr": 0.0},
            {"name": "shN", "params": [self.shN], "lr": 0.0},
        ]

    @torch.no_grad()
    def clamp_(self) -> None:
        if self.log_scale_max is not None:
            torch.minimum(self.log_scales, self.log_scale_max, out=self.log_scales)
        self.log_scales.clamp_(*self.log_scale_range)
        self.opacity_logits.clamp_(-12.0, 12.0)


@dataclass(frozen=True)
class StagePlan:
    """One training stage as data: which parameter groups learn, what the loss is, when it stops.

    photometric: False, Stage I (silhouettes at `preset.mask_scale`, plus photo-consistency when the preset weighs
        it); True, Stage II (random-background composites at `preset.image_scale`, mask, SH smoothness, fill).
    splats_fixed: only the pose learns, so the splats are evaluated once for the whole stage.
    The displacement smoothness joins the loss wherever the splats' normal moves learn. The stage's cap is
    `preset.iters_<name>`; it stops early when `preset.plateau` and its window's loss gain falls under
    `preset.plateau_rel_tol[stage]` (in Stage II only once dropout is over: the final fit uses every splat).
    """

    name: str
    trainable: tuple[str, ...]
    photometric: bool
    splats_fixed: bool = False


STAGE_PLANS = (
    StagePlan("pose", ("pose", "pose_camera"), photometric=False, splats_fixed=True),
    StagePlan("deform", ("pose", "pose_camera", "deformation", "displacement"), photometric=False),
    StagePlan("photo", ("pose", "pose_camera", "deformation", "displacement", "scales", "opacities", "sh0", "shN"), photometric=True),
)
DECAYING_GROUPS = ("pose", "pose_camera")  # their rate decays over a stage to `preset.pose_lr_final` of its start
REPORT_WINDOW = 20  # iterations averaged into a stage's reported `total_last_window`


class Plateau:
    """Stops a stage once the mean loss of the last `window` iterations improves on the window
    before it by less than `rel_tol` (relative). Single-view losses are noisy; whole windows are not."""

    def __init__(self, window: int, rel_tol: float):
        self.window = window
        self.rel_tol = rel_tol
        self.history: list[float] = []

    def update(self, loss: float) -> bool:
        self.history.append(loss)
        w = self.window
        if len(self.history) < 2 * w or len(self.history) % w:
            return False
        prev = float(np.mean(self.history[-2 * w : -w]))
        cur = float(np.mean(self.history[-w:]))
        return prev - cur < self.rel_tol * max(abs(prev), 1e-12)


@dataclass
class TrainState:
    """Where a run stands: the stage and iteration it is at, and what the finished stages reported.
    Only plain values, so a checkpoint holds it without pickled objects."""

    stage: int = 0  # index into STAGE_PLANS
    it: int = 0  # iterations done in that stage
    iterations: dict[str, int] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    losses: dict[str, dict] = field(default_factory=dict)
    skipped: int = 0
    plateau: list[float] = field(default_factory=list)
    history: dict[str, list[float]] = field(default_factory=dict)
    stage2_start: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(doc: dict) -> TrainState:
        return TrainState(**doc)


@dataclass
class TrainResult:
    model: SplatModel
    losses: dict
    timings_s: dict
    iterations: dict
    skipped_steps: int
    history: dict = field(default_factory=dict)
    stage2_start: dict = field(default_factory=dict)  # which state Stage II started from, and why


class CheckpointStore(Protocol):
    """Where a run keeps its checkpoint: `load` returns what `save` stored last (None when nothing is there)."""

    def load(self) -> dict | None: ...

    def save(self, payload: dict) -> None: ...


def _set_trainable(model: SplatModel, plan: StagePlan, pose_scale: bool = True) -> None:
    for group in model.param_groups():
        for p in group["params"]:
            p.requires_grad_(group["name"] in plan.trainable)
    # The rig's scale learns only when the preset says so; per-camera residuals are SE(3).
    model.pose.rig_log_scale.requires_grad_("pose" in plan.trainable and pose_scale)


def _grads_finite(params) -> bool:
    """Whether every gradient is finite, from one float64 sum per gradient: a sum is finite exactly when all its
    elements are (inf - inf is nan; float32 values cannot overflow a float64 sum), without a mask per gradient."""
    sums = [p.grad.sum(dtype=torch.float64) for p in params if p.grad is not None]
    return not sums or bool(torch.isfinite(torch.stack(sums)).all())


def _fingerprint(preset: Preset, splats: CanonicalSplats, views: Views) -> dict:
    # The splats' digest, not only their count: a checkpoint's per-splat rows fit only the splats they were trained
    # on, in their order (an engine that lays them out otherwise, or another draw, must start over).
    layout = hashlib.sha256(np.ascontiguousarray(splats.means, np.float32).tobytes()).hexdigest()
    return {
        "preset": preset.to_dict(),
        "num_splats": len(splats),
        "splats": layout,
        "views": int(len(views.images)),
        "c2w": np.round(views.c2w, 9).tolist(),
    }


@torch.no_grad()
def _recolor(model: SplatModel, splats: CanonicalSplats, views: Views, c2w_init: torch.Tensor) -> None:
    """SH DC from the training images projected at the Stage-I poses and deformed means: colours
    projected at the registration's poses would sit where the object was, not where it is now."""
    means = model.means().numpy()
    viewmats = model.viewmats(c2w_init, torch.arange(len(views.images))).numpy().astype(np.float64)
    rgb = project_colors(means, splats.normals, views.images, views.masks, viewmats, views.Ks)
    seen = ~np.all(rgb == 0.5, axis=1)
    model.sh0[torch.from_numpy(seen), 0] = torch.tensor(rgb_to_sh_dc(rgb[seen]), dtype=torch.float32)


@torch.no_grad()
def _consistency_weights(model: SplatModel, splats: CanonicalSplats, views: Views, c2w_init: torch.Tensor) -> torch.Tensor:
    """Which training views see which splats [V, N], at the current pose and field (full resolution, inside the masks)."""
    viewmats = model.viewmats(c2w_init, torch.arange(len(views.images))).numpy().astype(np.float64)
    h, w = views.masks.shape[1:]
    visible, _ = point_visibility(model.means().numpy(), splats.normals, viewmats, views.Ks, w, h, views.masks)
    return visibility_weights(visible)


@torch.no_grad()
def _stage2_objective(model: SplatModel, splats: CanonicalSplats, views: Views, c2w_init: torch.Tensor, data, preset: Preset) -> float:
    """Stage II's loss over all training views (grey background, no dropout) right after recolouring."""
    _recolor(model, splats, views, c2w_init)
    imgs, cov, valid, ks, w, h = data
    idx = torch.arange(len(views.images))
    bg = torch.full((len(idx), 3), 0.5)
    rgb, alpha = render(model.gaussians(), model.viewmats(c2w_init, idx), ks, w, h, bg)
    return float(
        photometric_loss(rgb, composite(imgs, cov, bg), preset.lambda_dssim, valid=valid) + preset.lambda_mask * mask_l1(alpha, cov, valid)
    )


def _choose_stage2_start(
    model: SplatModel, opt, splats: CanonicalSplats, views: Views, c2w_init: torch.Tensor, data, preset: Preset
) -> dict:
    """Stage II starts from the Stage-I pose and field, or from the registration's pose and an identity field when
    that explains the training photographs better: silhouettes of a CAD model that is not the photographed object
    can pull the pose off the texture. Starting from the registration resets the pose correction, zeroes the
    field's head and drops their Adam state; each splat's own normal moves (and their Adam state), its scales,
    opacities and colours stay as Stage I left them. Returns both objective values and the choice."""
    trained = _stage2_objective(model, splats, views, c2w_init, data, preset)
    kept = {k: v.clone() for k, v in model.state_dict().items()}
    model.pose.reset_()
    with torch.no_grad():
        model.field.mlp.head.weight.zero_()
        model.field.mlp.head.bias.zero_()
    registered = _stage2_objective(model, splats, views, c2w_init, data, preset)
    if registered < trained:
        for p in list(model.pose.parameters()) + list(model.field.parameters()):
            opt.state.pop(p, None)
        start = "registration"
    else:
        model.load_state_dict(kept)
        start = "stage1"
    return {"start": start, "objective_stage1": trained, "objective_registration": registered}


@dataclass
class _Run:
    """What every stage of one run shares."""

    model: SplatModel
    opt: Adam
    splats: CanonicalSplats
    views: Views
    preset: Preset
    c2w_init: torch.Tensor
    mask_data: ViewBatch
    photo_data: ViewBatch
    sh_graph: tuple
    rng: np.random.Generator
    gen: torch.Generator
    batch: int
    pc_images: torch.Tensor | None = None
    pc_ks: torch.Tensor | None = None

    @property
    def num_views(self) -> int:
        return len(self.views.images)


def _silhouette_loss(run: _Run, sel, gaussians: tuple, viewmats: torch.Tensor, pc_weights) -> tuple[torch.Tensor, dict]:
    """Stage I: L_mask on the rendered alpha (+ λ photo-consistency of the surface)."""
    _, cov, valid, ks, w, h = run.mask_data
    means, quats, scales, opac, _ = gaussians
    # The silhouette renders carry no colour channel: the rasterizer composites the transmittance alone, with the same
    # alphas and gradients as a zero colour.
    _, alpha, _ = rasterize(means, quats, scales, opac, torch.zeros(len(means), 0), viewmats, ks[sel], w, h, eps2d=run.preset.eps2d)
    l_mask = mask_l1(alpha, cov[sel], None if valid is None else valid[sel])
    loss, last = l_mask, {"mask": l_mask}
    if pc_weights is not None:
        l_pc = consistency_loss(sample_colors(run.pc_images[sel], means, viewmats, run.pc_ks[sel]), pc_weights[sel])
        loss = loss + run.preset.lambda_consistency * l_pc
        last["consistency"] = l_pc
    return loss, last


def _photometric_loss(
    run: _Run, it: int, idx: torch.Tensor, sel, gaussians: tuple, viewmats: torch.Tensor, targets
) -> tuple[torch.Tensor, dict]:
    """Stage II: L_rgb on a random-background composite (dropout on the colour render) + λ_mask L_mask + λ_SH L_SH (+ λ_fill L_fill)."""
    preset = run.preset
    _, cov, valid, ks, w, h = run.photo_data
    target_fg, target_bg_weight, in_mask = targets
    means, quats, scales, opac, sh = gaussians
    on_photo = None if valid is None else valid[sel]
    bg = torch.rand(len(idx), 3, generator=run.gen)
    p = dropout_fraction(it, preset.dropout_anneal, preset.dropout_p0)
    active = dropout_active(len(means), p, run.gen)
    rgb, alpha, _ = rasterize(
        means,
        quats,
        scales,
        opac,
        sh,
        viewmats,
        ks[sel],
        w,
        h,
        sh_degree=run.model.sh_degree,
        backgrounds=bg,
        active=active,
        eps2d=preset.eps2d,
    )
    if active is not None:
        # The silhouette is supervised on every splat: dropout regularises appearance only.
        _, alpha, _ = rasterize(means, quats, scales, opac, torch.zeros(len(means), 0), viewmats, ks[sel], w, h, eps2d=preset.eps2d)
    # Render and target are both the background wherever no splat reaches and the mask is 0.
    support = (alpha.detach()[..., 0] > 0) | in_mask[sel]
    target = torch.addcmul(target_fg[sel], bg[:, None, None, :], target_bg_weight[sel])
    l_rgb = photometric_loss(rgb, target, preset.lambda_dssim, support=support, valid=on_photo)
    l_mask, l_fill = silhouette_losses(alpha, cov[sel], on_photo)
    l_sh = sh_neighbour_loss(sh, run.sh_graph)
    loss = l_rgb + preset.lambda_mask * l_mask + preset.lambda_sh * l_sh
    last = {"rgb": l_rgb, "mask": l_mask, "sh": l_sh, "dropout": torch.tensor(p)}
    if preset.lambda_fill:
        loss = loss + preset.lambda_fill * l_fill
        last["fill"] = l_fill
    return loss, last


def _step(run: _Run, plan: StagePlan, loss: torch.Tensor, trainable: list, state: TrainState) -> float:
    """One optimizer step on `loss`; a non-finite loss or gradient skips it (counted). Returns the loss value."""
    opt, model = run.opt, run.model
    opt.zero_grad(set_to_none=True)
    value = float(loss.detach())
    if math.isfinite(value):
        loss.backward()
    if math.isfinite(value) and _grads_finite(trainable):
        opt.step()
        if plan.photometric and run.preset.shn_decay:
            with torch.no_grad():
                model.shN.mul_(1.0 - run.preset.lr.shN.at(plan.name) * run.preset.shn_decay)
        model.clamp_()
    else:
        state.skipped += 1
    return value


def _stage_setup(run: _Run, plan: StagePlan, state: TrainState) -> dict:
    """What a stage computes once before its iterations: the groups' rates, the consistency weights, the Stage II
    start and targets, the fixed splats of a pose-only stage."""
    preset, model = run.preset, run.model
    _set_trainable(model, plan, preset.pose_scale)
    decaying = []
    for group in run.opt.param_groups:
        group["lr"] = preset.lr.at(group["name"], plan.name)
        if group["name"] in DECAYING_GROUPS:
            decaying.append((group, group["lr"]))
    setup: dict = {"decaying": decaying, "pc_weights": None, "targets": None, "fixed": None}
    if not plan.photometric and preset.lambda_consistency > 0:
        setup["pc_weights"] = _consistency_weights(model, run.splats, run.views, run.c2w_init)
    if plan.photometric:
        if state.it == 0:
            state.stage2_start = _choose_stage2_start(model, run.opt, run.splats, run.views, run.c2w_init, run.photo_data, preset)
        cov = run.photo_data.coverage
        setup["targets"] = (*composite_parts(run.photo_data.images, cov), cov > 0)
    if plan.splats_fixed:
        with torch.no_grad():
            setup["fixed"] = model.gaussians().activated()
    return setup


def _run_stage(run: _Run, si: int, state: TrainState, save: Callable[[], None], progress: ProgressFn | None) -> None:
    """Stage `si` of `STAGE_PLANS` from `state.it` to its cap or its plateau."""
    plan, preset, model = STAGE_PLANS[si], run.preset, run.model
    setup = _stage_setup(run, plan, state)
    cap = getattr(preset, f"iters_{plan.name}")
    plateau = Plateau(window=max(preset.plateau_window[0], cap // preset.plateau_window[1]), rel_tol=preset.plateau_rel_tol[si])
    plateau.history = list(state.plateau)
    hist = state.history.setdefault(plan.name, [])
    t0 = time.perf_counter() - state.timings.get(plan.name, 0.0)
    trainable = [p for g in run.opt.param_groups for p in g["params"]]
    last: dict = {}
    it = state.it
    while it < cap:
        for group, lr0 in setup["decaying"]:
            group["lr"] = lr0 * preset.pose_lr_final ** (it / max(cap, 1))
        v = run.num_views
        idx = torch.arange(v) if run.batch == v else torch.from_numpy(run.rng.choice(v, run.batch, replace=False))
        # Every view in the batch: the stacks themselves, not an indexed copy of each per iteration.
        sel = slice(None) if run.batch == v else idx
        gaussians = setup["fixed"] if plan.splats_fixed else model.gaussians().activated()
        viewmats = model.viewmats(run.c2w_init, idx)
        if plan.photometric:
            loss, last = _photometric_loss(run, it, idx, sel, gaussians, viewmats, setup["targets"])
        else:
            loss, last = _silhouette_loss(run, sel, gaussians, viewmats, setup["pc_weights"])
        if preset.lambda_displacement and "displacement" in plan.trainable:
            l_disp = neighbour_smoothness(model.normal_moves(), run.sh_graph)
            loss = loss + preset.lambda_displacement * l_disp
            last["displacement"] = l_disp
        value = _step(run, plan, loss, trainable, state)
        it += 1
        hist.append(value)
        state.it = it
        done = preset.plateau and math.isfinite(value) and (not plan.photometric or it >= preset.dropout_anneal) and plateau.update(value)
        state.plateau = plateau.history
        state.timings[plan.name] = time.perf_counter() - t0
        if preset.checkpoint_every and it % preset.checkpoint_every == 0:
            save()
        if progress is not None:
            progress(plan.name, it, cap, value)
        if done:
            break
    state.timings[plan.name] = time.perf_counter() - t0
    state.iterations[plan.name] = it
    state.losses[plan.name] = {k: float(val.detach()) for k, val in last.items()}
    # A stage that ran no iteration (an ablation) has no loss to report: null, not NaN (twin.json is strict JSON).
    state.losses[plan.name]["total_last_window"] = float(np.mean(hist[-REPORT_WINDOW:])) if hist else None


def _start(views: Views, splats: CanonicalSplats, preset: Preset, seed: int) -> _Run:
    v = len(views.images)
    model = SplatModel(splats, preset, v, preset.pose_mode, seed)
    # Adam's per-parameter state is created lazily, so one optimizer serves all stages: groups that are frozen in a
    # stage have no gradient and are skipped. The fused step runs one kernel over every parameter (the same update
    # to rounding); `adam.Adam` is torch's update without torch.optim's class.
    opt = Adam(model.param_groups(), eps=preset.adam_eps, fused=True)
    run = _Run(
        model,
        opt,
        splats,
        views,
        preset,
        torch.tensor(views.c2w, dtype=torch.float64),
        views.resized(preset.mask_scale),
        views.resized(preset.image_scale),
        neighbour_graph(surface_neighbours(splats.means, splats.normals, preset.sh_neighbours)),
        np.random.default_rng(seed),
        torch.Generator().manual_seed(seed),
        v if preset.views_per_iter <= 0 else min(v, preset.views_per_iter),
    )
    if preset.lambda_consistency > 0:
        run.pc_images = blurred(torch.tensor(views.images, dtype=torch.float32), preset.consistency_blur_px)
        run.pc_ks = torch.tensor(views.Ks, dtype=torch.float32)
    return run


def train(
    views: Views,
    splats: CanonicalSplats,
    preset: Preset,
    *,
    seed: int = 0,
    progress: ProgressFn | None = None,
    checkpoint: CheckpointStore | None = None,
    on_stage_end: Callable[[str, SplatModel], None] | None = None,
) -> TrainResult:
    """Run the stages of `STAGE_PLANS` (Stage I: pose, then pose + deformation; Stage II: photometric) on `views`,
    in `preset.pose_mode`.

    progress(stage, iteration, cap, loss) is called after every iteration. With `checkpoint`, the run resumes
    from what it holds when that matches this run (same configuration, splats, views), and saves to it as it
    goes; the caller removes it once the twin is saved.
    """
    run = _start(views, splats, preset, seed)
    state = TrainState()
    fp = _fingerprint(preset, splats, views)
    saved = checkpoint.load() if checkpoint is not None else None
    if saved is not None and saved.get("fingerprint") == fp:
        run.model.load_state_dict(saved["model"])
        run.opt.load_state_dict(saved["optimizer"])
        run.rng.bit_generator.state = saved["rng"]
        run.gen.set_state(saved["torch_rng"])
        state = TrainState.from_dict(saved["state"])

    def save() -> None:
        if checkpoint is not None:
            checkpoint.save(
                {
                    "fingerprint": fp,
                    "model": run.model.state_dict(),
                    "optimizer": run.opt.state_dict(),
                    "rng": run.rng.bit_generator.state,
                    "torch_rng": run.gen.get_state(),
                    "state": state.to_dict(),
                }
            )

    for si in range(state.stage, len(STAGE_PLANS)):
        _run_stage(run, si, state, save, progress)
        state.stage, state.it, state.plateau = si + 1, 0, []
        save()
        if on_stage_end is not None:
            on_stage_end(STAGE_PLANS[si].name, run.model)
    return TrainResult(run.model, state.losses, state.timings, state.iterations, state.skipped, state.history, state.stage2_start)

"""Baselines run in the same harness as the method (paper 4.4): masked vanilla 3DGS and the sphere init.

Masked vanilla 3DGS (Kerbl et al. 2023, as gsplat's DefaultStrategy implements it): random points
in the masks' visual hull, every Gaussian parameter learnable (means included), the densify/prune
schedule (clone small / split large Gaussians whose view-space positional gradient exceeds a
threshold, periodic opacity reset, prune transparent and oversized ones), SH degree raised every
`sh_interval` iterations, a random background per iteration with the photograph composited over
the same colour by its mask, L1 + D-SSIM. Same images and poses as the method; it works in the
capture's own frame, so its twin's registration is the identity.

The sphere initialisation (paper 4.4.2) replaces the CAD mesh by a sphere at the point closest to
all optical axes whose projected area matches the masks' mean area (`sphere_mesh_for_views`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch
import trimesh
from scipy.optimize import brentq
from scipy.spatial import cKDTree
from torch import nn

from calibration.camera import Camera
from calibration.sim3 import Sim3
from calibration.so3 import quat_to_matrix
from reconstruction.adam import Adam
from reconstruction.gaussians import EPS2D_3DGS, Gaussians
from reconstruction.losses import composite, photometric_loss
from reconstruction.render import num_sh_bases, rasterize
from reconstruction.splats import SH_C0
from reconstruction.twin import Twin, TwinCamera

# ------------------------------------------------------------------------------------ sphere init


def optical_axes_point(cameras: Sequence[Camera]) -> np.ndarray:
    """The point [3] with the least summed squared distance to every camera's optical axis.

    Axis i passes through centre c_i along d_i (c2w's z column); the distance of p to it is
    |(I - d d^T)(p - c)|, so p solves sum_i (I - d_i d_i^T) p = sum_i (I - d_i d_i^T) c_i.
    """
    if len(cameras) < 2:
        raise ValueError("the optical axes of fewer than two cameras do not meet in a point")
    a, b = np.zeros((3, 3)), np.zeros(3)
    for cam in cameras:
        d = cam.c2w[:3, 2] / np.linalg.norm(cam.c2w[:3, 2])
        proj = np.eye(3) - np.outer(d, d)
        a += proj
        b += proj @ cam.center
    if np.linalg.cond(a) > 1e8:
        raise ValueError("the cameras' optical axes are parallel: they do not meet in a point")
    return np.linalg.solve(a, b)


def sphere_projected_area(camera: Camera, centre: np.ndarray, radius: float) -> float:
    """Pixel area of the disc a sphere covers when centred on the camera's line of sight at the
    distance of `centre`: the cone of half-angle asin(r/D) meets the image in a disc of radius
    f tan(asin(r/D)) = f r / sqrt(D^2 - r^2), so the area is pi fx fy r^2 / (D^2 - r^2)."""
    d2 = float(np.sum((np.asarray(centre) - camera.center) ** 2))
    return math.pi * camera.K[0, 0] * camera.K[1, 1] * radius**2 / max(d2 - radius**2, 1e-300)


def sphere_radius_for_masks(cameras: Sequence[Camera], masks: np.ndarray, centre: np.ndarray) -> float:
    """Radius whose mean projected area over the views equals the masks' mean area (pixels)."""
    target = float(np.mean([m.sum() for m in masks]))
    if target <= 0:
        raise ValueError("every mask is empty: there is no object to size the sphere to")
    r_max = min(float(np.linalg.norm(np.asarray(centre) - c.center)) for c in cameras) * (1 - 1e-9)

    def gap(r: float) -> float:
        return float(np.mean([sphere_projected_area(c, centre, r) for c in cameras])) - target

    return float(brentq(gap, 1e-12 * r_max, r_max, xtol=1e-12 * r_max, rtol=1e-10))


def sphere_mesh_for_views(cameras: Sequence[Camera], masks: np.ndarray, subdivisions: int = 4) -> trimesh.Trimesh:
    """Paper 4.4.2's generic initialisation, for the engine to use as the 'CAD mesh'.

    cameras: V >= 2 pinhole cameras (any common frame); masks: [V, H, W] bool. Returns an icosphere
    (10 * 4^subdivisions + 2 vertices) in the cameras' frame, centred at `optical_axes_point` with
    `sphere_radius_for_masks`' radius.
    """
    if len(cameras) != len(masks):
        raise ValueError(f"got {len(cameras)} cameras and {len(masks)} masks; they must match")
    centre = optical_axes_point(cameras)
    radius = sphere_radius_for_masks(cameras, masks, centre)
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    mesh.apply_translation(centre)
    return mesh


# ------------------------------------------------------------------------------------ vanilla 3DGS


def visual_hull_points(
    cameras: Sequence[Camera], masks: np.ndarray, n: int, rng: np.random.Generator, *, max_rounds: int = 50
) -> np.ndarray:
    """n points [n, 3] uniform in the masks' visual hull (inside every mask that sees them).

    Candidates are drawn in the cube of side 3r around the sphere estimate (centre, r) of
    `sphere_mesh_for_views`; a point outside a view's image is not carved by that view.
    """
    centre = optical_axes_point(cameras)
    half = 1.5 * sphere_radius_for_masks(cameras, masks, centre)
    kept: list[np.ndarray] = []
    total = 0
    for _ in range(max_rounds):
        pts = centre + rng.uniform(-half, half, (max(4 * n, 1024), 3))
        inside = np.ones(len(pts), bool)
        for cam, mask in zip(cameras, masks):
            uv, z = cam.project(pts)
            px = np.floor(np.nan_to_num(uv, nan=-1.0)).astype(np.int64)
            seen = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
            hit = np.zeros(len(pts), bool)
            hit[seen] = mask[px[seen, 1], px[seen, 0]]
            inside &= hit | ~seen
        kept.append(pts[inside])
        total += int(inside.sum())
        if total >= n:
            break
    pts = np.concatenate(kept)
    if len(pts) < n:
        raise ValueError("the masks' visual hull is empty: the masks do not agree on where the object is")
    return pts[:n]


@dataclass(frozen=True)
class VanillaConfig:
    """The original 3DGS recipe (gsplat's DefaultStrategy numbers at 30k iterations).

    `scaled(iterations)` shrinks every iteration count of the schedule in proportion, so a short CPU
    run keeps the recipe's shape: densify over the first half, ten opacity resets, SH ramp.
    """

    iterations: int = 30_000
    init_points: int = 100_000
    init_opacity: float = 0.1
    max_sh_degree: int = 3
    sh_interval: int = 1000
    refine_start: int = 500
    refine_stop: int = 15_000
    refine_every: int = 100
    reset_every: int = 3000
    grow_grad2d: float = 0.0002
    grow_scale3d: float = 0.01  # of the scene scale: larger Gaussians split, smaller ones clone
    prune_opacity: float = 0.005
    prune_scale3d: float = 0.1  # of the scene scale, applied after the first opacity reset
    lambda_dssim: float = 0.2
    eps2d: float = EPS2D_3DGS  # 3DGS's screen-space dilation; drawn with the same in evaluation
    lr_means: float = 1.6e-4  # times the scene scale, decayed exponentially to 1% at the end
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacities: float = 5e-2
    lr_sh0: float = 2.5e-3
    lr_shN: float = 2.5e-3 / 20
    max_gaussians: int = 1_000_000  # a guard for CPU memory, never reached by the recipe's objects

    def scaled(self, iterations: int, init_points: int | None = None) -> VanillaConfig:
        f = iterations / self.iterations

        def s(x: int) -> int:
            return max(1, int(round(x * f)))

        return replace(
            self,
            iterations=iterations,
            sh_interval=s(self.sh_interval),
            refine_start=s(self.refine_start),
            refine_stop=s(self.refine_stop),
            refine_every=s(self.refine_every),
            reset_every=s(self.reset_every),
            init_points=self.init_points if init_points is None else init_points,
        )


class GaussianParams(nn.Module):
    """Learnable 3DGS: means [N, 3], log_scales [N, 3], quats [N, 4], opacity_logits [N], sh0 [N, 1, 3], shN [N, K-1, 3]."""

    NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh0", "shN")

    def __init__(self, means: np.ndarray, rgb: np.ndarray, sh_degree: int, opacity: float):
        super().__init__()
        n = len(means)
        dist, _ = cKDTree(means).query(means, k=min(4, n))
        d = np.sqrt(np.mean(np.asarray(dist).reshape(n, -1)[:, 1:] ** 2, axis=1)) if n > 1 else np.ones(n)
        d = np.maximum(d, 1e-7)
        f32 = torch.float32
        self.means = nn.Parameter(torch.tensor(means, dtype=f32))
        self.log_scales = nn.Parameter(torch.tensor(np.log(d)[:, None].repeat(3, 1), dtype=f32))
        self.quats = nn.Parameter(torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n, dtype=f32))
        self.opacity_logits = nn.Parameter(torch.full((n,), math.log(opacity / (1 - opacity)), dtype=f32))
        self.sh0 = nn.Parameter(torch.tensor((rgb - 0.5) / SH_C0, dtype=f32)[:, None, :])
        self.shN = nn.Parameter(torch.zeros(n, num_sh_bases(sh_degree) - 1, 3, dtype=f32))

    def __len__(self) -> int:
        return self.means.shape[0]


def _adam(params: GaussianParams, cfg: VanillaConfig, scene_scale: float) -> Adam:
    lrs = {
        "means": cfg.lr_means * scene_scale,
        "log_scales": cfg.lr_scales,
        "quats": cfg.lr_quats,
        "opacity_logits": cfg.lr_opacities,
        "sh0": cfg.lr_sh0,
        "shN": cfg.lr_shN,
    }
    return Adam([{"name": k, "params": [getattr(params, k)], "lr": lrs[k]} for k in GaussianParams.NAMES], eps=1e-15)


@torch.no_grad()
def _update_params(params: GaussianParams, opt: Adam, keep: torch.Tensor, new: dict[str, torch.Tensor]) -> None:
    """Keeps rows `keep` [N] bool of every parameter and appends `new` rows; Adam moments follow the
    kept rows and start at zero for the new ones (as Inria's densification does)."""
    for group in opt.param_groups:
        name = group["name"]
        old = group["params"][0]
        extra = new[name]
        p = nn.Parameter(torch.cat([old.data[keep], extra]))
        state = opt.state.pop(old, None)
        if state:
            for key in ("exp_avg", "exp_avg_sq"):
                state[key] = torch.cat([state[key][keep], torch.zeros_like(extra)])
            opt.state[p] = state
        group["params"] = [p]
        setattr(params, name, p)


@torch.no_grad()
def densify_and_prune(
    params: GaussianParams,
    opt: Adam,
    grad2d_mean: torch.Tensor,
    cfg: VanillaConfig,
    scene_scale: float,
    *,
    prune_large: bool,
    gen: torch.Generator,
) -> dict[str, int]:
    """One refinement step: clone, split, prune. grad2d_mean: [N] mean view-space positional gradient
    norm (in NDC units, as Inria's threshold expects). Returns how many were cloned/split/pruned."""
    n = len(params)
    max_scale = torch.exp(params.log_scales).max(-1).values
    high = grad2d_mean > cfg.grow_grad2d
    small = max_scale <= cfg.grow_scale3d * scene_scale
    room = max(cfg.max_gaussians - n, 0)
    clone = high & small
    split = high & ~small
    if int(clone.sum()) + int(split.sum()) > room:  # the memory guard: keep the strongest gradients
        order = torch.argsort(torch.where(high, grad2d_mean, -1.0), descending=True)[: room // 2]
        chosen = torch.zeros(n, dtype=torch.bool)
        chosen[order] = True
        clone, split = clone & chosen, split & chosen
    # Split: two samples from each large Gaussian, scales / 1.6; the original goes.
    sel = torch.nonzero(split)[:, 0]
    scales = torch.exp(params.log_scales[sel])
    rot = torch.from_numpy(quat_to_matrix(params.quats[sel].numpy())).to(params.means.dtype)
    samples = torch.randn(2, len(sel), 3, generator=gen) * scales
    new_means = (params.means[sel] + torch.einsum("nij,snj->sni", rot, samples)).reshape(-1, 3)
    new = {
        "means": torch.cat([params.means[clone], new_means]),
        "log_scales": torch.cat([params.log_scales[clone], (params.log_scales[sel] - math.log(1.6)).repeat(2, 1)]),
    }
    for name in ("quats", "opacity_logits", "sh0", "shN"):
        t = getattr(params, name)
        new[name] = torch.cat([t[clone], t[sel].repeat(2, *([1] * (t.dim() - 1)))])
    _update_params(params, opt, ~split, new)
    # Prune: transparent, and after the first reset also oversized in world space.
    prune = torch.sigmoid(params.opacity_logits) < cfg.prune_opacity
    if prune_large:
        prune |= torch.exp(params.log_scales).max(-1).values > cfg.prune_scale3d * scene_scale
    if bool(prune.all()):
        prune[torch.argmax(params.opacity_logits)] = False  # never prune to nothing
    empty = {name: getattr(params, name)[:0] for name in GaussianParams.NAMES}
    _update_params(params, opt, ~prune, empty)
    return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": int(prune.sum())}


@torch.no_grad()
def reset_opacity(params: GaussianParams, opt: Adam, value: float = 0.01) -> None:
    """Clamp every opacity to at most `value` and forget its Adam moments (Inria's reset)."""
    params.opacity_logits.clamp_(max=math.log(value / (1 - value)))
    for group in opt.param_groups:
        if group["name"] == "opacity_logits":
            state = opt.state.get(group["params"][0])
            if state:
                state["exp_avg"].zero_()
                state["exp_avg_sq"].zero_()


@dataclass
class VanillaResult:
    """Trained Gaussians (numpy, float32) in the cameras' frame plus what the schedule did."""

    gaussians: Gaussians
    config: VanillaConfig
    num_gaussians: list[tuple[int, int]]  # (iteration, count) after init and after each refinement
    events: dict[str, int]  # totals cloned / split / pruned / opacity resets
    losses: list[float]
    wall_s: float


def train_vanilla_3dgs(
    images: np.ndarray,
    masks: np.ndarray,
    cameras: Sequence[Camera],
    cfg: VanillaConfig = VanillaConfig(),
    *,
    seed: int = 0,
    progress: Callable[[int, int, float, int], None] | None = None,
) -> VanillaResult:
    """Masked vanilla 3DGS on training views: images [V, H, W, 3] float in [0, 1], masks [V, H, W] bool,
    V pinhole cameras (their frame is the result's frame). progress(iteration, total, loss, N)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    gen = torch.Generator().manual_seed(seed)
    scene_scale = _scene_scale(cameras)
    pts = visual_hull_points(cameras, masks, cfg.init_points, rng)
    params = GaussianParams(pts, rng.random((len(pts), 3)), cfg.max_sh_degree, cfg.init_opacity)
    opt = _adam(params, cfg, scene_scale)
    lr_means0 = cfg.lr_means * scene_scale
    imgs, msks, viewmats, Ks = _view_tensors(images, masks, cameras)
    h, w = masks.shape[1:]
    grad_accum = torch.zeros(len(params))
    grad_count = torch.zeros(len(params))
    history = [(0, len(params))]
    events = {"cloned": 0, "split": 0, "pruned": 0, "opacity_resets": 0}
    losses = []
    for it in range(1, cfg.iterations + 1):
        _decay_means_lr(opt, lr_means0, it, cfg.iterations)
        degree = min(cfg.max_sh_degree, (it - 1) // cfg.sh_interval)
        v = int(rng.integers(len(cameras)))
        bg = torch.rand(1, 3, generator=gen)
        rgb, meta = _render_view(params, viewmats[v : v + 1], Ks[v : v + 1], w, h, degree, bg, cfg.eps2d)
        loss = photometric_loss(rgb, composite(imgs[v : v + 1], msks[v : v + 1], bg), cfg.lambda_dssim)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        losses.append(float(loss.detach()))
        if it < cfg.refine_stop:
            _accumulate_screen_grad(meta, grad_accum, grad_count, w, h)
        opt.step()
        if it < cfg.refine_stop and it > cfg.refine_start and it % cfg.refine_every == 0:
            stats = densify_and_prune(
                params,
                opt,
                grad_accum / grad_count.clamp_min(1),
                cfg,
                scene_scale,
                prune_large=it > cfg.reset_every,
                gen=gen,
            )
            for k, val in stats.items():
                events[k] += val
            grad_accum = torch.zeros(len(params))
            grad_count = torch.zeros(len(params))
            history.append((it, len(params)))
        if it < cfg.refine_stop and it % cfg.reset_every == 0:
            reset_opacity(params, opt)
            events["opacity_resets"] += 1
        if progress:
            progress(it, cfg.iterations, losses[-1], len(params))
    history.append((cfg.iterations, len(params)))
    sh = torch.cat([params.sh0, params.shN], 1)
    gaussians = Gaussians.from_arrays(params.means, params.quats, params.log_scales, params.opacity_logits, sh, cfg.eps2d)
    return VanillaResult(gaussians, cfg, history, events, losses, time.perf_counter() - t0)


def _scene_scale(cameras: Sequence[Camera]) -> float:
    """Inria's scene extent: 1.1 x the largest camera distance from the cameras' mean centre."""
    centres = np.stack([c.center for c in cameras])
    return 1.1 * float(np.linalg.norm(centres - centres.mean(0), axis=1).max())


def _view_tensors(
    images: np.ndarray, masks: np.ndarray, cameras: Sequence[Camera]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The training views as tensors: images [V, H, W, 3] float32, masks [V, H, W] bool, viewmats [V, 4, 4] and
    intrinsics [V, 3, 3] float32."""
    imgs = torch.tensor(np.asarray(images, np.float32))
    msks = torch.tensor(np.asarray(masks, bool))
    viewmats = torch.tensor(np.stack([c.viewmat for c in cameras]), dtype=torch.float32)
    Ks = torch.tensor(np.stack([c.K for c in cameras]), dtype=torch.float32)
    return imgs, msks, viewmats, Ks


def _decay_means_lr(opt: Adam, lr_means0: float, it: int, iterations: int) -> None:
    """The means' learning rate at iteration `it` (1-based): `lr_means0` decayed exponentially to 1 % at the last."""
    for group in opt.param_groups:
        if group["name"] == "means":
            group["lr"] = lr_means0 * 0.01 ** ((it - 1) / max(iterations - 1, 1))


def _render_view(
    params: GaussianParams, viewmat: torch.Tensor, K: torch.Tensor, w: int, h: int, degree: int, bg: torch.Tensor, eps2d: float
) -> tuple[torch.Tensor, dict]:
    """One view [1, H, W, 3] of the Gaussians at SH `degree` over background `bg` [1, 3] (viewmat [1, 4, 4], K [1, 3, 3]),
    and the rasterizer's meta, whose screen-space means keep their gradient (`_accumulate_screen_grad`)."""
    sh = torch.cat([params.sh0, params.shN], 1)[:, : num_sh_bases(degree)]
    rgb, _, meta = rasterize(
        params.means,
        params.quats,
        torch.exp(params.log_scales),
        torch.sigmoid(params.opacity_logits),
        sh,
        viewmat,
        K,
        w,
        h,
        sh_degree=degree,
        backgrounds=bg,
        eps2d=eps2d,
    )
    meta["means2d"].retain_grad()
    return rgb, meta


def _accumulate_screen_grad(meta: dict, grad_accum: torch.Tensor, grad_count: torch.Tensor, w: int, h: int) -> None:
    """Add each Gaussian's positional gradient norm from the view just rendered (`meta`) to `grad_accum` [N] and count
    the view in `grad_count` [N], for the Gaussians it saw: the positional gradient in NDC units (pixels * size / 2),
    which densification averages over the views that saw each Gaussian."""
    g2d = meta["means2d"].grad[0].to(torch.float32) * torch.tensor([w / 2.0, h / 2.0])
    seen = (meta["radii"][0] > 0).all(-1)
    grad_accum[seen] += g2d[seen].norm(dim=-1)
    grad_count[seen] += 1


def vanilla_twin(result: VanillaResult, cameras: Sequence[Camera], names: Sequence[str]) -> Twin:
    """The baseline as a twin (so `cadsplat evaluate` scores it like the method): identity
    registration (it lives in the capture's frame), no CAD anchoring (face index -1, one part)."""
    n = len(result.gaussians)
    cams = [TwinCamera(f"images/{name}.png", name, c.K, c.width, c.height, c.c2w) for name, c in zip(names, cameras)]
    return Twin(
        model_id="vanilla-3dgs",
        sim3_rig_to_object_init=Sim3.identity(),
        sim3_rig_to_object=Sim3.identity(),
        cameras=cams,
        preset="vanilla-3dgs",
        choices={"config": {"value": asdict(result.config), "why": "the original 3DGS recipe, schedule scaled to the iteration count"}},
        timings_s={"train": result.wall_s, "total": result.wall_s},
        losses={
            "photo": {"rgb": float(np.mean(result.losses[-20:]))},
            "events": result.events,
            "num_gaussians": [list(x) for x in result.num_gaussians],
        },
        gaussians=result.gaussians,
        means_canonical=result.gaussians.means,
        face_index=np.full(n, -1),
        barycentrics=np.zeros((n, 3), np.float32),
        part_label=np.zeros(n, np.int64),
        part_names=["object"],
        pose_mode="none",
    )

"""The evaluation protocol (paper section 4.3, SPEC "Evaluation protocol") applied to a twin.

Held-out cameras come in the capture's rig frame; they are mapped into the object frame through the
twin's refined `sim3_rig_to_object`, rendered over white with our rasterizer and scored with
`reconstruction.metrics.image_metrics`, once at the nominal pose and once after test-time pose
refinement: per view, only an SE(3) delta of that camera learns (`PoseCorrection`'s per-camera
mode) against the view's own photograph with the twin frozen, under the training loss of one view
(L1 + D-SSIM on RGB with the photograph composited on the render's background, plus the L1 mask
loss on alpha). The twin's arrays are only read: refinement cannot fit the twin to held-out views.

`run_protocol` is the whole harness the demo and the benchmarks share: reconstruct a capture, score the
twin on held-out views, measure its registration error against ground truth; one `ProtocolResult`.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from calibration.camera import Camera
from calibration.capture import load_views, read_capture
from calibration.sim3 import Sim3
from calibration.so3 import geodesic_angle_deg
from reconstruction.adam import Adam
from reconstruction.gaussians import WHITE, Gaussians, camera_batch, render
from reconstruction.losses import composite, mask_l1, photometric_loss
from reconstruction.metrics import image_metrics
from reconstruction.pose_correction import PoseCorrection, viewmats_from_c2w
from reconstruction.pose_metrics import registration_errors
from reconstruction.registration import RegistrationResult
from reconstruction.symmetry import NearSymmetry, near_symmetries
from reconstruction.twin import Twin, load_twin

PAPER_REFINE_STEPS = 400
REFINE_LR = 5e-4  # the paper's pose-correction learning rate (Table "Hyperparameters")
LAMBDA_DSSIM = 0.2
LAMBDA_MASK = 1.0
METRIC_KEYS = ("psnr", "ssim", "lpips", "flip", "mpsnr", "mssim", "mlpips", "mflip", "fgpsnr", "iou")


def _render_view(g: Gaussians, viewmat: torch.Tensor, camera: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """rgb [H, W, 3] over white and alpha [H, W] of `g` seen by `camera`'s intrinsics at viewmat [4, 4] (may carry gradients)."""
    _, Ks, width, height = camera_batch(camera)
    rgb, alpha = render(g, viewmat[None], Ks, width, height, WHITE)
    return rgb[0], alpha[0]


def view_loss(
    rgb: torch.Tensor,
    alpha: torch.Tensor,
    gt_rgb: torch.Tensor,
    gt_mask: torch.Tensor,
    background: torch.Tensor,
    *,
    lambda_dssim: float = LAMBDA_DSSIM,
    lambda_mask: float = LAMBDA_MASK,
) -> torch.Tensor:
    """The training loss of one view (`reconstruction.losses`): L_rgb + λ_mask L_mask.

    rgb [H, W, 3] is the render over `background` [3]; the photograph gt_rgb [H, W, 3] is composited
    over the same background with gt_mask [H, W], so background pixels compare like with like.
    """
    target = composite(gt_rgb[None], gt_mask[None], background)
    return photometric_loss(rgb[None], target, lambda_dssim) + lambda_mask * mask_l1(alpha[None], gt_mask[None])


@dataclass(frozen=True)
class Refinement:
    """Result of test-time refinement of one camera: refined c2w [4, 4] (float64), losses per step [steps]."""

    c2w: np.ndarray
    losses: np.ndarray
    rotation_deg: float  # how far the camera turned
    translation: float  # how far its centre moved (object-frame units)


def refine_camera_pose(
    g: Gaussians,
    camera: Camera,
    gt_rgb: np.ndarray,
    gt_mask: np.ndarray,
    *,
    steps: int = PAPER_REFINE_STEPS,
    lr: float = REFINE_LR,
) -> Refinement:
    """Test-time refinement: an SE(3) delta of `camera` (object frame) learns against its own view.

    Adam on the delta's 6D rotation and camera-axis translation, `lr` constant (the paper's pose
    learning rate), over white as the metrics render. Only the delta is handed to the optimizer and
    the splats carry no gradient, so the twin cannot change. Returns the pose of the lowest loss
    seen (the last step's pose may sit on an Adam oscillation).
    """
    correction = PoseCorrection(1, mode="per_camera")
    opt = Adam(correction.camera_parameters(), lr=lr)
    c2w0 = torch.as_tensor(camera.c2w, dtype=torch.float64)[None]
    target = torch.as_tensor(np.asarray(gt_rgb, np.float32))
    mask = torch.as_tensor(np.asarray(gt_mask, bool))
    background = torch.tensor(WHITE, dtype=torch.float32)
    losses = np.zeros(steps)
    best_loss, best_c2w = math.inf, camera.c2w.copy()
    for step in range(steps):
        c2w = correction(c2w0)
        rgb, alpha = _render_view(g, viewmats_from_c2w(c2w)[0], camera)
        loss = view_loss(rgb, alpha, target, mask, background)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        losses[step] = float(loss.detach())
        if losses[step] < best_loss:
            best_loss, best_c2w = losses[step], c2w.detach()[0].numpy().copy()
        opt.step()
    # The pose after the last update has not been scored; score it so it can win too.
    if steps:
        with torch.no_grad():
            c2w = correction(c2w0)
            rgb, alpha = _render_view(g, viewmats_from_c2w(c2w)[0], camera)
            final = float(view_loss(rgb, alpha, target, mask, background))
        if final < best_loss:
            best_c2w = c2w[0].numpy().copy()
    rot = float(geodesic_angle_deg(camera.c2w[:3, :3], best_c2w[:3, :3]))
    return Refinement(best_c2w, losses, rot, float(np.linalg.norm(best_c2w[:3, 3] - camera.c2w[:3, 3])))


def cameras_to_object(cameras: Sequence[Camera], sim3_rig_to_object: Sim3) -> list[Camera]:
    """Rig-frame cameras -> object-frame cameras through the registration (x_obj = s R x_rig + t)."""
    return [c.with_c2w(sim3_rig_to_object.apply_to_c2w(c.c2w)) for c in cameras]


def _finite(x: float) -> float | None:
    """JSON has no NaN/inf: a metric that is undefined (nan) or unbounded (inf, identical images) is None."""
    return float(x) if math.isfinite(x) else None


def average_metrics(per_view: Sequence[dict[str, float | None]]) -> dict[str, float | None]:
    """Mean of each metric over the views where it is defined (None where no view defines it)."""
    out: dict[str, float | None] = {}
    for key in METRIC_KEYS:
        values = [v[key] for v in per_view if v.get(key) is not None]
        out[key] = float(np.mean(values)) if values else None
    return out


def evaluate_views(
    g: Gaussians,
    cameras: Sequence[Camera],
    images: np.ndarray,
    masks: np.ndarray,
    *,
    names: Sequence[str] | None = None,
    refine_steps: int = PAPER_REFINE_STEPS,
    refine_lr: float = REFINE_LR,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Scores `g` on held-out views, with and (when refine_steps > 0) without test-time refinement.

    Args:
        cameras: V object-frame pinhole cameras; images [V, H, W, 3] float in [0, 1]; masks [V, H, W] bool.
        names: view names for the report (default view indices).
        progress: called with (views done, V) after each view.

    Returns:
        {"views": [{name, metrics, metrics_refined?, refine?, timings_s}], "mean", "mean_refined"?,
        "timings_s": {render, refine, metrics, per_view_render_ms}}; metrics are `image_metrics`'
        keys, None where undefined (no overlap, empty eroded mask) or infinite (a perfect match).
    """
    if len(cameras) != len(images) or len(images) != len(masks):
        raise ValueError(f"got {len(cameras)} cameras, {len(images)} images and {len(masks)} masks; they must match")
    if len(cameras) == 0:
        raise ValueError("there are no held-out views to evaluate")
    names = [str(i) for i in range(len(cameras))] if names is None else list(names)
    views, t_render, t_refine, t_metrics = [], 0.0, 0.0, 0.0
    for i, (cam, img, msk) in enumerate(zip(cameras, images, masks)):
        img, msk = cam.crop(img), cam.crop(msk)
        if not np.any(msk):
            raise ValueError(f"held-out view {names[i]} has an empty mask: the object is not in it")
        entry: dict = {"name": names[i]}
        t0 = time.perf_counter()
        with torch.no_grad():
            rgb, alpha = _render_view(g, torch.as_tensor(cam.viewmat), cam)
        t1 = time.perf_counter()
        entry["metrics"] = {k: _finite(v) for k, v in image_metrics(rgb, alpha, img, msk).items()}
        t2 = time.perf_counter()
        t_render, t_metrics = t_render + t1 - t0, t_metrics + t2 - t1
        timings = {"render": t1 - t0, "metrics": t2 - t1}
        if refine_steps > 0:
            ref = refine_camera_pose(g, cam, img, msk, steps=refine_steps, lr=refine_lr)
            t3 = time.perf_counter()
            with torch.no_grad():
                rgb, alpha = _render_view(g, torch.as_tensor(np.linalg.inv(ref.c2w)), cam)
            entry["metrics_refined"] = {k: _finite(v) for k, v in image_metrics(rgb, alpha, img, msk).items()}
            t4 = time.perf_counter()
            entry["refine"] = {
                "steps": refine_steps,
                "rotation_deg": ref.rotation_deg,
                "translation": ref.translation,
                "translation_pct_of_distance": 100.0 * ref.translation / max(float(np.linalg.norm(cam.center)), 1e-12),
                "loss_first": float(ref.losses[0]),
                "loss_last": float(ref.losses[-1]),
                "c2w_object": ref.c2w.tolist(),
            }
            timings |= {"refine": t3 - t2, "metrics_refined": t4 - t3}
            t_refine, t_metrics = t_refine + t3 - t2, t_metrics + t4 - t3
        entry["timings_s"] = timings
        views.append(entry)
        if progress:
            progress(i + 1, len(cameras))
    out = {
        "views": views,
        "mean": average_metrics([v["metrics"] for v in views]),
        "timings_s": {
            "render": t_render,
            "refine": t_refine,
            "metrics": t_metrics,
            "per_view_render_ms": 1000.0 * t_render / len(views),
        },
    }
    if refine_steps > 0:
        out["mean_refined"] = average_metrics([v["metrics_refined"] for v in views])
    return out


def registration_report(c2w_est: np.ndarray, c2w_gt: np.ndarray, symmetries: Sequence[np.ndarray] | None = None) -> dict:
    """Registration errors of training cameras (object-frame c2w [N, 4, 4], estimated vs truth) as JSON-ready numbers."""
    err = registration_errors(np.linalg.inv(np.asarray(c2w_est, np.float64)), np.linalg.inv(np.asarray(c2w_gt, np.float64)), symmetries)
    return {
        "rotation_deg_median": err["rotation_deg_median"],
        "center_pct_median": err["center_pct_median"],
        "rotation_deg": err["rotation_deg"].tolist(),
        "center_pct": err["center_pct"].tolist(),
        "symmetry": err["symmetry"],
    }


def half_turn(axis: str) -> np.ndarray:
    """The 180-degree rotation [3, 3] about the object frame's 'x', 'y' or 'z' axis (a symmetry to allow)."""
    if axis not in ("x", "y", "z"):
        raise ValueError(f"symmetry axis must be x, y or z, got {axis!r}")
    return np.diag([1.0 if a == axis else -1.0 for a in "xyz"])


def twin_near_symmetries(twin, tolerance_m: float) -> list[NearSymmetry]:
    """Near-symmetries of a twin's CAD mesh (object frame, metres) within `tolerance_m`: the poses the
    twin's model cannot tell apart. Raises TwinError (a ValueError) when the twin has no CAD mesh."""
    mesh = twin.load_mesh_cad()
    return near_symmetries(mesh.vertices, mesh.faces, tolerance_m)


def select_views(n: int, max_views: int | None) -> list[int]:
    """Indices of at most `max_views` of n views, evenly spread over the capture order (all when None)."""
    if max_views is None or max_views >= n:
        return list(range(n))
    if max_views < 1:
        raise ValueError(f"max_views must be at least 1, got {max_views}")
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, max_views)})


def gt_train_poses(twin_cameras: Sequence, gt: dict) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Pairs a twin's training cameras with `gt.json`'s true object-frame poses.

    The synthetic rig names train view i `cam{i:02d}`; a twin made from a subset of views (farthest-
    point sampling) keeps those names, so cameras are matched by name, never by position.
    Returns (estimated c2w [M, 4, 4], true c2w [M, 4, 4], names [M]).
    """
    truth = np.asarray(gt["train_c2w_object"], np.float64)
    est, ref, names = [], [], []
    for cam in twin_cameras:
        name = str(cam.camera_id)
        if not (name.startswith("cam") and name[3:].isdigit() and int(name[3:]) < len(truth)):
            raise ValueError(f"twin camera {name!r} has no ground-truth pose in gt.json (expected names cam00..cam{len(truth) - 1:02d})")
        est.append(cam.c2w_object_opencv)
        ref.append(truth[int(name[3:])])
        names.append(name)
    if not names:
        raise ValueError("the twin lists no training cameras to compare with gt.json")
    return np.stack(est), np.stack(ref), names


def evaluate_twin(
    twin,
    cameras_rig: Sequence[Camera],
    images: np.ndarray,
    masks: np.ndarray,
    *,
    names: Sequence[str] | None = None,
    refine_steps: int = PAPER_REFINE_STEPS,
    refine_lr: float = REFINE_LR,
    gt: dict | None = None,
    symmetries: Sequence[np.ndarray] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """The whole protocol for a `Twin` on held-out views whose cameras are in the rig frame.

    Cameras go to the object frame through the twin's refined `sim3_rig_to_object`; with `gt` (the
    synthetic rig's gt.json dict) the twin's training cameras are also scored against the truth,
    against the closest of `symmetries` (object-frame rotations [3, 3]) when given.
    Returns `evaluate_views`' report plus "registration" when `gt` is given and "num_splats".
    """
    t0 = time.perf_counter()
    g = twin.gaussians
    cams = cameras_to_object(cameras_rig, twin.sim3_rig_to_object)
    report = evaluate_views(g, cams, images, masks, names=names, refine_steps=refine_steps, refine_lr=refine_lr, progress=progress)
    report["num_splats"] = int(twin.num_splats)
    if gt is not None:
        est, ref, cam_names = gt_train_poses(twin.cameras, gt)
        report["registration"] = {"cameras": cam_names, **registration_report(est, ref, symmetries)}
    report["timings_s"]["total"] = time.perf_counter() - t0
    return report


@dataclass(frozen=True)
class ProtocolResult:
    """One run of the protocol: the twin, how it scored on held-out views and how well it registered.

    registration: the engine's `RegistrationResult` (None when an existing twin was scored).
    heldout_views: indices into the held-out capture. report: `evaluate_twin`'s report.
    With ground truth (else None), registration errors of the training cameras (`registration_report`):
    reg_init at the retrieval's Sim(3), before training, over every view of the training capture;
    reg_refined at the trained twin's cameras, modulo the given symmetries; reg_raw the same without them.
    timings_s: reconstruct (the twin's own total; the wall time when it records none), evaluate (wall).
    """

    twin: Twin
    registration: RegistrationResult | None
    heldout_views: list[int]
    report: dict
    reg_init: dict | None
    reg_refined: dict | None
    reg_raw: dict | None
    timings_s: dict[str, float]

    @property
    def mean(self) -> dict[str, float | None]:
        return self.report["mean"]

    @property
    def mean_refined(self) -> dict[str, float | None] | None:
        return self.report.get("mean_refined")


def run_protocol(
    capture: str | os.PathLike,
    heldout: str | os.PathLike,
    library: str | os.PathLike | None,
    out_dir: str | os.PathLike,
    *,
    preset: str = "cpu",
    views: Sequence[int] | None = None,
    pose_mode: str | None = None,
    init: str = "cad",
    ablations: Sequence[str] = (),
    overrides: Mapping[str, Any] | None = None,
    seed: int = 0,
    heldout_views: int | Sequence[int] | None = None,
    refine_steps: int = PAPER_REFINE_STEPS,
    gt: dict | None = None,
    symmetries: Sequence[np.ndarray] | None = None,
    reuse: bool = False,
    overwrite: bool = False,
    progress: Callable[[str, int, int, float], None] | None = None,
    log: Callable[[str], None] | None = None,
    heldout_progress: Callable[[int, int], None] | None = None,
) -> ProtocolResult:
    """The whole protocol: reconstruct the twin of the capture at `capture` into `out_dir`, score it on the
    held-out capture at `heldout` (`evaluate_twin`, nominal and after `refine_steps` of test-time
    refinement) and, with `gt` (the synthetic rig's gt.json dict), measure its registration error
    against the truth, modulo `symmetries` (object-frame transforms the object maps onto itself).

    preset, views, pose_mode, init, ablations, overrides, seed, progress, log and overwrite go to
    `pipeline.reconstruct_capture`; with `reuse`, a twin already in `out_dir` is scored instead of trained again.
    heldout_views: how many held-out views, evenly spread (`select_views`), or their indices; all when None.
    heldout_progress is called with (0, V) when scoring starts, then with (views done, V).
    """
    from reconstruction.pipeline import reconstruct_capture

    out = os.fspath(out_dir)
    t0 = time.perf_counter()
    rec = None
    if not (reuse and os.path.exists(os.path.join(out, "twin.json"))):
        rec = reconstruct_capture(
            capture,
            library,
            out,
            preset=preset,
            views=views,
            pose_mode=pose_mode,
            seed=seed,
            progress=progress,
            log=log,
            overwrite=overwrite,
            init=init,
            ablations=ablations,
            overrides=overrides,
        )
    twin = load_twin(out) if rec is None else rec.twin
    trained_s = time.perf_counter() - t0

    t0 = time.perf_counter()
    idx, report = _score_heldout(twin, heldout, heldout_views, refine_steps, gt, symmetries, heldout_progress)
    evaluate_s = time.perf_counter() - t0
    reg_init = reg_refined = reg_raw = None
    if gt is not None:
        reg_init, reg_refined, reg_raw = _train_pose_errors(twin, capture, report, gt, symmetries)
    return ProtocolResult(
        twin=twin,
        registration=None if rec is None else rec.registration,
        heldout_views=idx,
        report=report,
        reg_init=reg_init,
        reg_refined=reg_refined,
        reg_raw=reg_raw,
        timings_s={"reconstruct": float(twin.timings_s.get("total", trained_s)), "evaluate": evaluate_s},
    )


def _score_heldout(
    twin: Twin,
    heldout: str | os.PathLike,
    heldout_views: int | Sequence[int] | None,
    refine_steps: int,
    gt: dict | None,
    symmetries: Sequence[np.ndarray] | None,
    progress: Callable[[int, int], None] | None,
) -> tuple[list[int], dict]:
    """The held-out views scored (their indices in the capture at `heldout`, and `evaluate_twin`'s report):
    `heldout_views` of them evenly spread (`select_views`), or those indices; all when None."""
    held = read_capture(heldout)
    count = heldout_views is None or isinstance(heldout_views, (int, np.integer))
    idx = select_views(len(held), heldout_views) if count else [int(i) for i in heldout_views]
    images, masks, cams = load_views(held, idx)
    if progress:
        progress(0, len(idx))
    report = evaluate_twin(
        twin,
        cams,
        images,
        masks,
        names=[held.frames[i].camera_id for i in idx],
        refine_steps=refine_steps,
        gt=gt,
        symmetries=symmetries,
        progress=progress,
    )
    return idx, report


def _train_pose_errors(
    twin: Twin, capture: str | os.PathLike, report: dict, gt: dict, symmetries: Sequence[np.ndarray] | None
) -> tuple[dict, dict, dict]:
    """`registration_report`s of the train cameras against the truth `gt`: placed by the registration alone (the
    capture's recorded cameras through the twin's initial Sim(3)), as the twin refined them (from `report`, modulo
    `symmetries`), and the raw refined ones."""
    train_c2w = np.stack([f.camera.c2w for f in read_capture(capture).frames])
    reg_init = registration_report(twin.sim3_rig_to_object_init.apply_to_c2w(train_c2w), np.array(gt["train_c2w_object"]), symmetries)
    return reg_init, report["registration"], registration_report(*gt_train_poses(twin.cameras, gt)[:2])

"""Capture + CAD library -> registration -> CAD-anchored splats -> two-stage training -> twin directory.

This is the I/O edge of the reconstruction engine: it reads the capture and the library, writes the
twin (and a checkpoint beside it while training), and records what it chose, why, and how long each
step took. The math lives in splats, deformation, pose_correction, losses and train. A registration,
masks or decoded images computed before (`cadsplat register`, the service's register step) are taken
as given, so nothing is masked or registered twice.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from calibration.camera import Camera
from calibration.capture import Capture, load_views, read_capture, rig_metres_per_unit
from calibration.sim3 import Sim3
from reconstruction.mesh_io import MeshParts, read_mesh_parts
from reconstruction.pose_correction import PER_CAMERA_ABOVE_PX, choose_pose_mode, extrinsics_error_px, residual_rates
from reconstruction.gaussians import Gaussians, camera_batch, render, straight_rgba
from reconstruction.presets import apply_ablations, resolve_preset, scene_stats
from reconstruction.quality import check_masks, check_registration
from reconstruction.registration import RegistrationResult, check_fits
from reconstruction.splats import CanonicalSplats, init_splats, project_colors
from reconstruction.surface import mask_overlap_offset, offset_along_normals, silhouette_surface, untangle
from reconstruction.train import ProgressFn, TrainResult, Views, train
from reconstruction.twin import Twin, TwinCamera, check_replaceable, save_twin, software_versions

Log = Callable[[str], None]
# The pose + deformation stage's cap from a sphere, in units of the preset's (CAD) cap.
SPHERE_DEFORM_FACTOR = 4


@dataclass
class Reconstruction:
    twin: Twin
    registration: object  # reconstruction.registration.RegistrationResult
    train: TrainResult
    splats: CanonicalSplats  # the initial state, before training


def model_parts(library, model_id: str) -> MeshParts:
    """The library model's mesh in metres, split into its named parts (one part named after the model if unnamed)."""
    entry = library.entry(model_id)
    parts = read_mesh_parts(entry.mesh_path)
    parts.vertices = parts.vertices * entry.scale_to_m
    if len(parts.part_names) == 1:
        parts.part_names = [model_id]
    return parts


def _views(capture: Capture, idx: list[int], images: np.ndarray | None, masks: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, list[Camera], str]:
    """Images [V, H, W, 3], masks [V, H, W] and pinhole cameras of views `idx`, and where the masks came from.

    `images`/`masks` given (one per capture view, undistorted, as `load_views`/`capture_masks` make them)
    are used as they are ("given"): only what was not given is decoded or computed, each file once."""
    from reconstruction.masks import capture_masks

    for name, given in (("images", images), ("masks", masks)):
        if given is not None and (len(given) != len(capture) or any(given.shape[1:3] != (f.camera.height, f.camera.width) for f in capture.frames)):
            raise ValueError(f"the given {name} are {given.shape[:3]}, not one per view of the capture at {capture.root} "
                             f"({len(capture)} views of {capture.frames[0].camera.width}x{capture.frames[0].camera.height})")
    every = idx == list(range(len(capture)))  # then the given arrays are used as they are, not copied
    if images is not None:
        if masks is None:
            raise ValueError("images are handed forward with their masks; give both or neither")
        cams = [capture.camera(i) for i in idx]
        return (images, masks, cams, "given") if every else (images[idx], masks[idx], cams, "given")
    images, own, cams = load_views(capture, idx, with_masks=masks is None)
    if masks is not None:
        return images, masks if every else masks[idx], cams, "given"
    if own is not None:
        return images, own, cams, "masks/"
    computed, source = capture_masks(capture, images, idx)
    return images, computed, cams, source


def metric_sim3(sim3_rig_to_object: Sim3, metres_per_unit: float, centre_object: np.ndarray) -> Sim3:
    """The registration with its scale set to the calibration's (`metres_per_unit`; object frame in
    metres), turned about the object's centre `centre_object` [3] so the object stays where the
    silhouettes put it. A silhouette fit's scale errs by a few % (thin and elongated parts: 2-6 %
    on the path-traced rig scenes); a metric rig measures it."""
    r = sim3_rig_to_object.rotation
    centre_rig = sim3_rig_to_object.inverse().apply(np.asarray(centre_object, np.float64)[None])[0]
    return Sim3(metres_per_unit, r, centre_object - metres_per_unit * r @ centre_rig)


def calibration_error_px(meta: dict, cams: Sequence[Camera], centre_rig: np.ndarray) -> float | None:
    """The capture's stated calibration uncertainty in pixels at the object (rig-frame centre [3]); None if unstated."""
    uncertainty = meta.get("calibration_uncertainty")
    if not isinstance(uncertainty, dict):
        return None
    metres_per_unit = rig_metres_per_unit(meta) or 1.0
    distance_m = metres_per_unit * np.linalg.norm(np.stack([c.c2w[:3, 3] for c in cams]) - centre_rig, axis=1)
    return extrinsics_error_px(uncertainty, np.array([c.K[0, 0] for c in cams]), distance_m)


def _scale_choice(metres_per_unit: float | None, reg: RegistrationResult) -> dict:
    if metres_per_unit is None:
        return {"value": float(reg.sim3_rig_to_object.scale), "why": "the rig frame has no metric scale: the registration's "
                "silhouette scale; the deformation field carries no uniform scaling"}
    return {"value": metres_per_unit, "why": "metric rig: the calibration's scale, fixed; a part whose size departs from its "
            "CAD model shows as a deformation"}


def sphere_registration(masks: np.ndarray, cams: Sequence[Camera]) -> tuple[RegistrationResult, MeshParts]:
    """The sphere initialisation as a registration: the sphere lives in the rig frame (identity Sim(3)),
    scored by its silhouette IoU in every view like a retrieved model."""
    from reconstruction.baselines import sphere_mesh_for_views
    from reconstruction.registration import REFINE_PX, Scorer

    t = time.perf_counter()
    mesh = sphere_mesh_for_views(cams, masks)
    parts = MeshParts(np.asarray(mesh.vertices), np.asarray(mesh.faces), np.zeros(len(mesh.faces), np.int64), ["sphere"])
    ious = Scorer(masks, list(cams), REFINE_PX)(parts.vertices, parts.faces, Sim3.identity())
    reg = RegistrationResult(model_id="sphere", sim3_rig_to_object=Sim3.identity(), per_view_iou=ious, score=float(ious.mean()),
                             alternatives=[], ambiguity=None, timings_s={"total": time.perf_counter() - t}, truncated_views=[],
                             scale_observable=True)
    return reg, parts


def reconstruct(
    capture: str | os.PathLike | Capture,
    library_path: str | os.PathLike | None,
    out_dir: str | os.PathLike,
    *,
    registration: RegistrationResult | None = None,
    masks: np.ndarray | None = None,
    images: np.ndarray | None = None,
    preset: str = "cpu",
    model_id: str | None = None,
    views: Sequence[int] | None = None,
    pose_mode: str | None = None,
    seed: int = 0,
    progress: ProgressFn | None = None,
    log: Log | None = None,
    overwrite: bool = False,
    init: str = "cad",
    ablations: Sequence[str] = (),
    overrides: Mapping[str, Any] | None = None,
) -> Reconstruction:
    """Reconstruct the twin of a capture; writes `out_dir` (atomically) and returns the twin.

    An interrupted run leaves `.<out_dir name>.checkpoint.pt` beside `out_dir`; running the same
    command again resumes from it. `views` picks training views by index; `model_id` skips retrieval
    and registers that library model only; `pose_mode` overrides the automatic choice.

    Work done before flows forward instead of being redone: `capture` may be an already read
    `Capture`; `registration` (of every capture view, on the capture's metric scale, e.g. from
    `RegistrationResult.from_dict` of reg.json) is used as given instead of registering; `masks`
    [V, H, W] bool and `images` [V, H, W, 3] (one per capture view, undistorted, as `capture_masks`
    and `load_views` make them) are used instead of decoding and masking the capture again. What was
    given is recorded in twin.json `choices` as "given".

    Evaluation switches: `init="sphere"` replaces retrieval and registration by the paper's generic
    sphere (section 4.4.2; `library_path` is then not read); `ablations` names entries of
    `presets.ABLATIONS`; `overrides` sets `Preset` fields after the preset is resolved. All three are
    recorded in twin.json `choices`.
    """
    from reconstruction.library import load_library
    from reconstruction.registration import register

    say = log or (lambda _msg: None)
    out = Path(out_dir)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} already exists; choose another --out or remove it")
    check_replaceable(out, overwrite)
    timings: dict[str, float] = {}
    t_all = time.perf_counter()
    torch.manual_seed(seed)

    t = time.perf_counter()
    if not isinstance(capture, Capture):
        capture = read_capture(capture)
    if init not in ("cad", "sphere"):
        raise ValueError(f"unknown init {init!r}; choose cad or sphere")
    if registration is not None:
        if init != "cad" or (model_id is not None and model_id != registration.model_id):
            raise ValueError(f"a given registration (of {registration.model_id!r}) replaces registering; "
                             "it takes neither --init sphere nor another --model")
        check_fits(registration, capture)
    idx = list(range(len(capture))) if views is None else list(views)
    images, masks, cams, mask_source = _views(capture, idx, images, masks)
    check_masks([c.crop(m) for c, m in zip(cams, masks)], names=[f"view {i} ({capture.frames[i].camera_id})" for i in idx])
    library = load_library(library_path) if init == "cad" else None
    timings["load"] = time.perf_counter() - t

    t = time.perf_counter()
    metric = rig_metres_per_unit(capture.meta, capture.root) if init == "cad" else None
    if library is None:
        reg, parts = sphere_registration(masks, cams)
    else:
        reg = registration
        if reg is None:
            say(f"registering {len(idx)} views against {len(library.models)} library models")
            reg = register(masks, cams, library, model_ids=[model_id] if model_id else None, seed=seed,
                           rig_metres_per_unit=metric)
            check_registration(reg.score, reg.alternatives, masks, len(library.models), reg.model_id)
        parts = model_parts(library, reg.model_id)
    timings["registration"] = time.perf_counter() - t
    say(f"registered {reg.model_id} (mean silhouette IoU {reg.score:.3f})")

    t = time.perf_counter()
    centre = 0.5 * (parts.vertices.min(0) + parts.vertices.max(0))
    sim3_start = reg.sim3_rig_to_object if metric is None else metric_sim3(reg.sim3_rig_to_object, metric, centre)
    c2w_init = sim3_start.apply_to_c2w(np.stack([c.c2w for c in cams]))
    stats = scene_stats(masks, c2w_init, centre)
    cfg, choices = resolve_preset(preset, stats)
    if init == "sphere":
        # A sphere is not the object: the field carves the whole shape, not a CAD model's few-% misfit (NeRS car,
        # held-out photos 1 / 2: Stage I's mask loss 0.051 after 100 iterations, 0.006 after 400; object-crop
        # PSNR 12.01 -> 14.33 and 13.42 -> 14.73 dB). The plateau test still stops it once carved.
        cfg = replace(cfg, iters_deform=SPHERE_DEFORM_FACTOR * cfg.iters_deform)
        choices["iteration_caps"] = {**choices["iteration_caps"], "value": {**choices["iteration_caps"]["value"], "deform": cfg.iters_deform},
                                     "why": choices["iteration_caps"]["why"] + f"; the pose + deformation stage {SPHERE_DEFORM_FACTOR}x "
                                     "longer from a sphere, which the field must carve into the object"}
    if ablations:
        cfg, choices["ablations"] = apply_ablations(cfg, list(ablations))
    if overrides:
        unknown = sorted(set(overrides) - set(cfg.to_dict()))
        if unknown:
            raise ValueError(f"unknown preset field {unknown[0]!r} in overrides")
        # Nested preset fields (the deformation field's config, the learning rates) merge into what was resolved.
        merged = {k: v if not isinstance(v, Mapping) else replace(cfg.field, **v) if k == "field" else {**cfg.lr, **v} if k == "lr" else v
                  for k, v in overrides.items()}
        cfg = replace(cfg, **merged)
        choices["overrides"] = {"value": dict(overrides), "why": "set by the caller after the preset was resolved"}
    if cfg.field.project_similarity:
        cfg = replace(cfg, field=replace(cfg.field, projection_keeps_scale=metric is not None))
    choices["scale"] = _scale_choice(metric, reg)
    if init == "sphere":
        choices["init"] = {"value": "sphere", "why": "paper 4.4.2: no CAD; an icosphere at the optical axes' meeting point, "
                           "sized so its projections match the masks' areas"}
    error_px = calibration_error_px(capture.meta, cams, reg.sim3_rig_to_object.inverse().apply(centre[None])[0])
    mode, why = choose_pose_mode(capture.meta, pose_mode, calibration_error_px=error_px)
    choices["pose_mode"] = {"value": mode, "why": why}
    lr, coarse = residual_rates(cfg.lr, capture.meta, error_px)
    if mode == "per_camera" and coarse:
        cfg = replace(cfg, lr=lr)
        choices["learning_rates"] = {"value": cfg.lr, "why": choices["learning_rates"]["why"] + "; poses rough or stated to be "
                                     f"off by more than {PER_CAMERA_ABOVE_PX:g} px: per-camera residuals at the rig's rate in the "
                                     "second Stage-I stage, kept in Stage II"}
    choices["masks"] = {"value": mask_source, "why": "computed once before reconstruct and handed to it" if mask_source == "given"
                        else "capture masks when present, else background subtraction"}
    Ks = np.stack([c.K for c in cams])
    viewmats = np.stack([np.linalg.inv(c) for c in c2w_init])
    probe = init_splats(parts.vertices, parts.faces, cfg.num_splats, sh_degree=cfg.sh_degree, face_part=parts.face_part, seed=seed)
    rgb = project_colors(probe.means, probe.normals, images, masks, viewmats, Ks)
    splats = init_splats(parts.vertices, parts.faces, cfg.num_splats, sh_degree=cfg.sh_degree, face_part=parts.face_part, rgb=rgb,
                         opacity=cfg.init_opacity, seed=seed)
    choices["sh_init"] = {"value": "projected", "why": "SH DC from the training images projected at the registered poses "
                          "(facing views, inside masks, z-buffered); neutral grey where no view sees a splat"}
    timings["init"] = time.perf_counter() - t

    ckpt = out.parent / f".{out.name}.checkpoint.pt"
    out.parent.mkdir(parents=True, exist_ok=True)
    sizes = np.array([(c.width, c.height) for c in cams])
    result = train(Views(images, masks, Ks, c2w_init, sizes), splats, cfg, pose_mode=mode, seed=seed, progress=progress, checkpoint=ckpt)
    for stage, secs in result.timings_s.items():
        timings[f"train_{stage}"] = secs
    choices["stage2_start"] = {"value": result.stage2_start.get("start"), "why": "Stage II starts from whichever of the Stage-I "
                               "pose+field and the registration gives the lower Stage-II loss on the training views", **result.stage2_start}
    choices["iterations"] = {"value": result.iterations, "why": "stages stop at their cap or when the loss plateaus" if cfg.plateau else "fixed schedule"}

    t = time.perf_counter()
    model = result.model
    with torch.no_grad():
        means = model.means().numpy()
        c2w_refined = model.pose(torch.tensor(c2w_init)).numpy()
        sh = model.sh().numpy()
    delta = model.pose.delta_sim3()
    sim3_refined: Sim3 = delta @ sim3_start
    twin_cams = [
        TwinCamera(capture.frames[i].file_path, capture.frames[i].camera_id, cams[j].K, cams[j].width, cams[j].height, c2w_refined[j])
        for j, i in enumerate(idx)
    ]
    losses = {stage: vals for stage, vals in result.losses.items()}
    losses["skipped_nonfinite_steps"] = result.skipped_steps
    twin = Twin(
        model_id=reg.model_id,
        sim3_rig_to_object_init=reg.sim3_rig_to_object,
        sim3_rig_to_object=sim3_refined,
        cameras=twin_cams,
        preset=cfg.name,
        choices=choices,
        timings_s=timings,
        losses=losses,
        gaussians=Gaussians.from_arrays(means, splats.gaussians.quats, model.log_scales, model.opacity_logits, sh, cfg.eps2d),
        means_canonical=splats.means,
        face_index=splats.face_index,
        barycentrics=splats.barycentrics,
        part_label=splats.part_label,
        part_names=parts.part_names,
        pose_mode=mode,
        versions=software_versions(),
    )
    renders = {Path(c.file_path).name: straight_rgba(*render(twin.gaussians, *camera_batch(c.camera), background=None))[0]
               for c in twin_cams}
    surface, _ = untangle(parts.vertices, silhouette_surface(parts.vertices + model.offsets_at(parts.vertices), parts.faces,
                                                             twin.gaussians), parts.faces)
    # The splats' rim blends past their own alpha-1/2 radius: the masks set the last, uniform step, measured on
    # the surface as it will be written (untangling smooths folded faces' moves, outwards or in).
    step = mask_overlap_offset(surface, parts.faces, [c.camera for c in twin_cams], masks, bracket=0.02 * float(model.field.radius))
    surface, untangled = untangle(parts.vertices, offset_along_normals(surface, parts.faces, step), parts.faces)
    deformed = MeshParts(surface, parts.faces, parts.face_part, parts.part_names)
    twin.choices["surface"] = {"value": "alpha 1/2, then the masks' overlap", "mask_step_mm": round(1000.0 * step, 3),
                               "untangled_vertices": int(np.sum(untangled)),
                               "why": "the deformed mesh moved out along its normals by the splats' median reach to alpha 1/2 "
                                      "(surface.silhouette_surface): the fit leaves their centres that far inside the object; "
                                      "then by the step at which its silhouettes best overlap the masks (surface.mask_overlap_offset); "
                                      "then, wherever a face came to cross another, the move smoothed over its neighbours, and pulled back "
                                      "towards the CAD where smoothing leaves a fold (surface.untangle)"}
    timings["export"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_all
    twin.choices["registration"] = {"value": reg.to_dict(), "source": "given" if registration is not None else "computed",
                                    "why": "silhouette consensus registration (paper 3.2)"
                                    + (", computed once before reconstruct and handed to it" if registration is not None else "")}
    save_twin(twin, out, deformation_state=model.field.export_state(), mesh_cad=parts, mesh_deformed=deformed,
              renders=renders, overwrite=overwrite)
    if ckpt.exists():
        ckpt.unlink()
    return Reconstruction(twin, reg, result, splats)

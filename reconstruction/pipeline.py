"""Views + registration + CAD mesh + configuration -> CAD-anchored splats -> two-stage training -> `Twin`.

`reconstruct` is the engine's one entry: it takes what was computed before in memory (the capture's
`CaptureViews`, its `RegistrationResult`, the model's `MeshParts`, a resolved `Preset`) and returns
the twin with what saving and reporting on it need, without touching a file. `configure` resolves
the configuration from the views and the registration; `reconstruct_capture` and `retrain_like`
are the edges a command, the service and the benchmarks call: they read the capture and the
library, place the checkpoint beside the output and save the twin. The math lives in splats,
deformation, pose_correction, losses and train.
"""

from __future__ import annotations

import io
import os
import pickle
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from calibration.capture import Capture, read_capture, rig_metres_per_unit
from calibration.fileio import atomic_write_bytes
from calibration.sim3 import Sim3
from reconstruction.gaussians import Gaussians, camera_batch, render, straight_rgba
from reconstruction.mesh_io import MeshParts, read_mesh_parts
from reconstruction.pose_correction import extrinsics_error_px
from reconstruction.presets import ConfigInputs, Preset, SceneStats, reasons, resolve_config, scene_stats
from reconstruction.quality import check_masks
from reconstruction.registration import RegistrationConfig, RegistrationResult, check_fits
from reconstruction.splats import CanonicalSplats, init_splats, project_colors
from reconstruction.surface import mask_overlap_offset, offset_along_normals, silhouette_surface, untangle
from reconstruction.train import CheckpointStore, ProgressFn, SplatModel, TrainResult, Views, train
from reconstruction.twin import Twin, TwinCamera, check_replaceable, object_up, save_twin, software_versions
from reconstruction.views import CaptureViews, capture_views

Log = Callable[[str], None]


@dataclass
class Reconstruction:
    """What `reconstruct` made, in memory: the twin, and what saving it (`save_reconstruction`) and reporting on it need."""

    twin: Twin
    registration: RegistrationResult
    train: TrainResult
    splats: CanonicalSplats  # the initial state, before training
    mesh_cad: MeshParts
    mesh_deformed: MeshParts
    renders: dict[str, np.ndarray]  # training image name -> RGBA float [H, W, 4]


class CheckpointError(ValueError):
    """A checkpoint beside the output that this engine will not load (one plain sentence)."""


class FileCheckpoint:
    """The checkpoint file `.<out name>.checkpoint.pt` beside a twin's output directory.

    It holds only tensors and plain values, and is read with `torch.load(weights_only=True)`: a file
    planted there that would run code when unpickled is refused, never executed."""

    def __init__(self, out_dir: str | os.PathLike):
        out = Path(out_dir)
        self.path = out.parent / f".{out.name}.checkpoint.pt"

    def load(self) -> dict | None:
        if not self.path.exists():
            return None
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # torch warns about a foreign pickle protocol before refusing it
                payload = torch.load(self.path, map_location="cpu", weights_only=True)
        except (pickle.UnpicklingError, RuntimeError, EOFError, ValueError, OSError) as e:
            raise CheckpointError(
                f"{self.path} is not a checkpoint this engine wrote (it does not load as tensors and plain values: "
                f"{type(e).__name__}); it was not loaded; remove it to start training over"
            ) from None
        return payload if isinstance(payload, dict) else None

    def save(self, payload: dict) -> None:
        buf = io.BytesIO()
        torch.save(payload, buf)
        atomic_write_bytes(self.path, buf.getvalue())

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)


def model_parts(library, model_id: str) -> MeshParts:
    """The library model's mesh in metres, split into its named parts (one part named after the model if unnamed)."""
    entry = library.entry(model_id)
    parts = read_mesh_parts(entry.mesh_path)
    parts.vertices = parts.vertices * entry.scale_to_m
    if len(parts.part_names) == 1:
        parts.part_names = [model_id]
    return parts


def metric_sim3(sim3_rig_to_object: Sim3, metres_per_unit: float, centre_object: np.ndarray) -> Sim3:
    """The registration with its scale set to the calibration's (`metres_per_unit`; object frame in
    metres), turned about the object's centre `centre_object` [3] so the object stays where the
    silhouettes put it. A silhouette fit's scale errs by a few % on thin and elongated parts; a
    metric rig measures it."""
    r = sim3_rig_to_object.rotation
    centre_rig = sim3_rig_to_object.inverse().apply(np.asarray(centre_object, np.float64)[None])[0]
    return Sim3(metres_per_unit, r, centre_object - metres_per_unit * r @ centre_rig)


def calibration_error_px(meta: dict, cams: Sequence, centre_rig: np.ndarray) -> float | None:
    """The capture's stated calibration uncertainty in pixels at the object (rig-frame centre [3]); None if unstated."""
    uncertainty = meta.get("calibration_uncertainty")
    if not isinstance(uncertainty, dict):
        return None
    distance_m = (rig_metres_per_unit(meta) or 1.0) * np.linalg.norm(np.stack([c.c2w[:3, 3] for c in cams]) - centre_rig, axis=1)
    return extrinsics_error_px(uncertainty, np.array([c.K[0, 0] for c in cams]), distance_m)


def sphere_registration(masks: np.ndarray, cams: Sequence) -> tuple[RegistrationResult, MeshParts]:
    """The sphere initialisation as a registration: the sphere lives in the rig frame (identity Sim(3)),
    scored by its silhouette IoU in every view like a retrieved model."""
    from reconstruction.baselines import sphere_mesh_for_views
    from reconstruction.registration import REFINE_PX, Scorer

    t = time.perf_counter()
    mesh = sphere_mesh_for_views(cams, masks)
    parts = MeshParts(np.asarray(mesh.vertices), np.asarray(mesh.faces), np.zeros(len(mesh.faces), np.int64), ["sphere"])
    ious = Scorer(masks, list(cams), REFINE_PX)(parts.vertices, parts.faces, Sim3.identity())
    reg = RegistrationResult(
        model_id="sphere",
        sim3_rig_to_object=Sim3.identity(),
        per_view_iou=ious,
        score=float(ious.mean()),
        alternatives=[],
        ambiguity=None,
        timings_s={"total": time.perf_counter() - t},
        truncated_views=[],
        scale_observable=True,
    )
    return reg, parts


def start_pose(registration: RegistrationResult, parts: MeshParts) -> tuple[Sim3, np.ndarray]:
    """(the Sim(3) training starts from, the object's centre [3]): on a metric rig (the registration's
    `rig_metres_per_unit`) the calibration's scale, turned about the object's centre."""
    centre = 0.5 * (parts.vertices.min(0) + parts.vertices.max(0))
    metric = registration.rig_metres_per_unit
    return (registration.sim3_rig_to_object if metric is None else metric_sim3(registration.sim3_rig_to_object, metric, centre)), centre


def configure(
    preset: str,
    views: CaptureViews,
    registration: RegistrationResult,
    parts: MeshParts,
    *,
    init: str = "cad",
    pose_mode: str | None = None,
    ablations: Sequence[str] = (),
    overrides: Mapping[str, Any] | None = None,
) -> tuple[Preset, ConfigInputs]:
    """The configuration of one reconstruction, resolved from what the views and the registration say
    (scene statistics at the start pose, calibration provenance and metric scale) and the caller's word."""
    sim3, centre = start_pose(registration, parts)
    stats = scene_stats(views.masks, sim3.apply_to_c2w(np.stack([c.c2w for c in views.cameras])), centre)
    meta = views.capture.meta
    centre_rig = registration.sim3_rig_to_object.inverse().apply(centre[None])[0]
    inputs = ConfigInputs(
        stats=stats,
        metric=registration.rig_metres_per_unit is not None,
        init=init,
        pose_source=meta.get("pose_source"),
        calibration_id=meta.get("calibration_id"),
        pose_mode=pose_mode,
        ablations=tuple(ablations),
        overrides=dict(overrides or {}),
        calibration_error_px=calibration_error_px(meta, views.cameras, centre_rig),
    )
    return resolve_config(preset, inputs), inputs


def inputs_from_dict(doc: Mapping[str, Any]) -> ConfigInputs:
    """`ConfigInputs` as twin.json records them (`asdict`)."""
    return ConfigInputs(
        **{
            **doc,
            "stats": SceneStats(**{**doc["stats"], "foreground_px": tuple(doc["stats"]["foreground_px"])}),
            "ablations": tuple(doc["ablations"]),
        }
    )


def _initial_splats(parts: MeshParts, views: CaptureViews, c2w: np.ndarray, config: Preset, seed: int) -> CanonicalSplats:
    """Splats on the CAD surface, their SH DC projected from the training images at the start poses c2w [V, 4, 4]."""
    Ks = np.stack([c.K for c in views.cameras])
    viewmats = np.stack([np.linalg.inv(c) for c in c2w])
    probe = init_splats(parts.vertices, parts.faces, config.num_splats, sh_degree=config.sh_degree, face_part=parts.face_part, seed=seed)
    rgb = project_colors(probe.means, probe.normals, views.images, views.masks, viewmats, Ks)
    return init_splats(
        parts.vertices,
        parts.faces,
        config.num_splats,
        sh_degree=config.sh_degree,
        face_part=parts.face_part,
        rgb=rgb,
        opacity=config.init_opacity,
        seed=seed,
    )


def _deformed_surface(
    parts: MeshParts, model: SplatModel, gaussians: Gaussians, cameras: list, masks: np.ndarray
) -> tuple[MeshParts, dict]:
    """The CAD mesh moved as the splats moved, out to their alpha-1/2 rim, then by the step the masks ask for."""
    surface, _ = untangle(
        parts.vertices, silhouette_surface(parts.vertices + model.offsets_at(parts.vertices), parts.faces, gaussians), parts.faces
    )
    # The splats' rim blends past their own alpha-1/2 radius: the masks set the last, uniform step, measured on
    # the surface as it will be written (untangling smooths folded faces' moves, outwards or in).
    step = mask_overlap_offset(surface, parts.faces, cameras, masks, bracket=0.02 * float(model.field.radius))
    surface, untangled = untangle(parts.vertices, offset_along_normals(surface, parts.faces, step), parts.faces)
    choice = {
        "value": "alpha 1/2, then the masks' overlap",
        "mask_step_mm": round(1000.0 * step, 3),
        "untangled_vertices": int(np.sum(untangled)),
        "why": "the deformed mesh moved out along its normals by the splats' median reach to alpha 1/2 "
        "(surface.silhouette_surface): the fit leaves their centres that far inside the object; "
        "then by the step at which its silhouettes best overlap the masks (surface.mask_overlap_offset); "
        "then, wherever a face came to cross another, the move smoothed over its neighbours, and pulled back "
        "towards the CAD where smoothing leaves a fold (surface.untangle)",
    }
    return MeshParts(surface, parts.faces, parts.face_part, parts.part_names), choice


def _outcomes(views: CaptureViews, registration: RegistrationResult, result: TrainResult, config: Preset, source: str) -> dict:
    """What the run found (twin.json `choices` beside the configuration's reasons)."""
    metric = registration.rig_metres_per_unit
    scale = (
        {
            "value": float(registration.sim3_rig_to_object.scale),
            "why": "the rig frame has no metric scale: the registration's "
            "silhouette scale; the deformation field carries no uniform scaling",
        }
        if metric is None
        else {
            "value": metric,
            "why": "metric rig: the calibration's scale, fixed; a part whose size departs from its CAD model shows as a deformation",
        }
    )
    return {
        "scale": scale,
        "masks": {
            "value": views.mask_source,
            "why": "computed once before reconstruct and handed to it"
            if views.mask_source == "given"
            else "capture masks when present, else background subtraction",
        },
        "sh_init": {
            "value": "projected",
            "why": "SH DC from the training images projected at the registered poses "
            "(facing views, inside masks, z-buffered); neutral grey where no view sees a splat",
        },
        "stage2_start": {
            "value": result.stage2_start.get("start"),
            "why": "Stage II starts from whichever of the Stage-I pose+field and the "
            "registration gives the lower Stage-II loss on the training views",
            **result.stage2_start,
        },
        "iterations": {
            "value": result.iterations,
            "why": "stages stop at their cap or when the loss plateaus" if config.plateau else "fixed schedule",
        },
        "registration": {
            "value": registration.to_dict(),
            "source": source,
            "why": "silhouette consensus registration (paper 3.2)"
            + (", computed once before reconstruct and handed to it" if source == "given" else ""),
        },
    }


def reconstruct(
    views: CaptureViews,
    registration: RegistrationResult,
    parts: MeshParts,
    config: Preset,
    *,
    seed: int = 0,
    inputs: ConfigInputs | None = None,
    registration_source: str = "computed",
    progress: ProgressFn | None = None,
    checkpoint: CheckpointStore | None = None,
    timings_s: Mapping[str, float] | None = None,
) -> Reconstruction:
    """The twin of `views` (training views of one capture) registered by `registration` to the mesh `parts`
    (object frame, metres), trained with `config`; nothing is read or written (`checkpoint`, when given, is
    the caller's store). `inputs`: what `config` was resolved from (recorded, and its reasons generated, in
    twin.json); `timings_s`: the caller's earlier steps, recorded beside this run's."""
    timings = dict(timings_s or {})
    t0 = t = time.perf_counter()
    torch.manual_seed(seed)
    sim3_start, _ = start_pose(registration, parts)
    c2w_init = sim3_start.apply_to_c2w(np.stack([c.c2w for c in views.cameras]))
    splats = _initial_splats(parts, views, c2w_init, config, seed)
    timings["init"] = time.perf_counter() - t
    result = train(
        Views(views.images, views.masks, np.stack([c.K for c in views.cameras]), c2w_init, views.sizes),
        splats,
        config,
        seed=seed,
        progress=progress,
        checkpoint=checkpoint,
    )
    timings.update({f"train_{stage}": secs for stage, secs in result.timings_s.items()})
    t = time.perf_counter()
    model = result.model
    with torch.no_grad():
        means, c2w, sh = model.means().numpy(), model.pose(torch.tensor(c2w_init)).numpy(), model.sh().numpy()
    frames = views.capture.frames
    cameras = [
        TwinCamera(frames[i].file_path, frames[i].camera_id, cam.K, cam.width, cam.height, c2w[j])
        for j, (i, cam) in enumerate(zip(views.indices, views.cameras))
    ]
    choices = {
        **(reasons(config, inputs) if inputs is not None else {}),
        **_outcomes(views, registration, result, config, registration_source),
    }
    twin = Twin(
        model_id=registration.model_id,
        sim3_rig_to_object_init=registration.sim3_rig_to_object,
        sim3_rig_to_object=model.pose.delta_sim3() @ sim3_start,
        cameras=cameras,
        preset=config.name,
        choices=choices,
        timings_s=timings,
        losses={**result.losses, "skipped_nonfinite_steps": result.skipped_steps},
        gaussians=Gaussians.from_arrays(means, splats.gaussians.quats, model.log_scales, model.opacity_logits, sh, config.eps2d),
        means_canonical=splats.means,
        face_index=splats.face_index,
        barycentrics=splats.barycentrics,
        part_label=splats.part_label,
        part_names=parts.part_names,
        pose_mode=config.pose_mode,
        versions=software_versions(),
        config=config.to_dict(),
        training={"seed": seed, "views": list(views.indices), "inputs": None if inputs is None else asdict(inputs)},
    )
    if "up_rig" in views.capture.meta:
        twin.up_object = object_up(views.capture.meta["up_rig"], twin.sim3_rig_to_object)
    renders = {Path(c.file_path).name: straight_rgba(*render(twin.gaussians, *camera_batch(c.camera), background=None))[0] for c in cameras}
    deformed, twin.choices["surface"] = _deformed_surface(parts, model, twin.gaussians, [c.camera for c in cameras], views.masks)
    timings["export"] = time.perf_counter() - t
    timings["total"] = sum(v for k, v in (timings_s or {}).items() if k != "total") + time.perf_counter() - t0
    return Reconstruction(twin, registration, result, splats, parts, deformed, renders)


def save_reconstruction(rec: Reconstruction, out_dir: str | os.PathLike, *, overwrite: bool = False) -> Path:
    """Write the twin of `rec` to `out_dir` (atomically, `twin.save_twin`)."""
    return save_twin(rec.twin, out_dir, mesh_cad=rec.mesh_cad, mesh_deformed=rec.mesh_deformed, renders=rec.renders, overwrite=overwrite)


@dataclass
class Prepared:
    """A capture's views, registered, with the mesh to anchor the splats on: what `configure` and `reconstruct` take."""

    views: CaptureViews
    registration: RegistrationResult
    parts: MeshParts
    source: str  # "computed" or "given"
    timings_s: dict[str, float]


def prepare(
    capture: str | os.PathLike | Capture | CaptureViews,
    library_path: str | os.PathLike | None,
    *,
    indices: Sequence[int] | None = None,
    registration: RegistrationResult | None = None,
    model_id: str | None = None,
    init: str = "cad",
    seed: int = 0,
    registration_config: RegistrationConfig | None = None,
    log: Log | None = None,
) -> Prepared:
    """Read the capture (unless its views are given, decoded once before) and register it: through `register_views`
    under `registration_config` (rig.toml's [registration]; `model_id`: that model only), as `registration` gives
    (of every capture view), or to the generic sphere."""
    from reconstruction.library import load_library
    from reconstruction.registration import RegistrationConfig, register_views

    say = log or (lambda _msg: None)
    t = time.perf_counter()
    if init not in ("cad", "sphere"):
        raise ValueError(f"unknown init {init!r}; choose cad or sphere")
    if registration is not None and (init != "cad" or (model_id is not None and model_id != registration.model_id)):
        raise ValueError(
            f"a given registration (of {registration.model_id!r}) replaces registering; it takes neither --init sphere nor another --model"
        )
    if isinstance(capture, CaptureViews):
        views = capture if indices is None else capture.subset([capture.indices.index(i) for i in indices])
    else:
        views = capture_views(capture if isinstance(capture, Capture) else read_capture(capture), indices)
    # A given registration is of every capture view, or of exactly the training views (a twin's own record, `retrain_like`).
    if registration is not None and not (len(registration.per_view_iou) == len(views) < len(views.capture)):
        check_fits(registration, views.capture)
    check_masks([c.crop(m) for c, m in zip(views.cameras, views.masks)], names=views.names)
    library = load_library(library_path) if init == "cad" else None
    timings = {"load": time.perf_counter() - t}
    t = time.perf_counter()
    if library is None:
        reg, parts = sphere_registration(views.masks, views.cameras)
    else:
        reg = registration
        if reg is None:
            say(f"registering {len(views)} views against {len(library.models)} library models")
            reg = register_views(views, library, registration_config or RegistrationConfig(), model_id=model_id, seed=seed)
        parts = model_parts(library, reg.model_id)
    timings["registration"] = time.perf_counter() - t
    say(f"registered {reg.model_id} (mean silhouette IoU {reg.score:.3f})")
    return Prepared(views, reg, parts, "given" if registration is not None else "computed", timings)


def _train_and_save(
    prep: Prepared, config: Preset, inputs: ConfigInputs | None, out: Path, *, seed: int, progress: ProgressFn | None, overwrite: bool
) -> Reconstruction:
    checkpoint = FileCheckpoint(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rec = reconstruct(
        prep.views,
        prep.registration,
        prep.parts,
        config,
        seed=seed,
        inputs=inputs,
        registration_source=prep.source,
        progress=progress,
        checkpoint=checkpoint,
        timings_s=prep.timings_s,
    )
    save_reconstruction(rec, out, overwrite=overwrite)
    checkpoint.remove()
    return rec


def reconstruct_capture(
    capture: str | os.PathLike | Capture | CaptureViews,
    library_path: str | os.PathLike | None,
    out_dir: str | os.PathLike,
    *,
    registration: RegistrationResult | None = None,
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
    registration_config: RegistrationConfig | None = None,
) -> Reconstruction:
    """Reconstruct the twin of a capture into `out_dir` (written atomically) and return it.

    An interrupted run leaves `.<out_dir name>.checkpoint.pt` beside `out_dir`; running the same command
    again resumes from it. `capture` may be already decoded views (`CaptureViews`), `registration` one of
    every capture view (e.g. `RegistrationResult.from_dict` of reg.json): both are used as given. `views`
    picks training views by capture index; `model_id` registers that library model only. `init="sphere"`
    replaces the CAD by the paper's generic sphere (section 4.4.2; the library is not read); `pose_mode`,
    `ablations` and `overrides` are inputs of the configuration (`presets.resolve_config`); `registration_config`
    is rig.toml's [registration] (`registration.register_views`).
    """
    out = Path(out_dir)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} already exists; choose another --out or remove it")
    check_replaceable(out, overwrite)
    prep = prepare(
        capture,
        library_path,
        indices=views,
        registration=registration,
        model_id=model_id,
        init=init,
        seed=seed,
        registration_config=registration_config,
        log=log,
    )
    config, inputs = configure(
        preset, prep.views, prep.registration, prep.parts, init=init, pose_mode=pose_mode, ablations=ablations, overrides=overrides
    )
    return _train_and_save(prep, config, inputs, out, seed=seed, progress=progress, overwrite=overwrite)


def retrain_like(
    twin: Twin,
    capture: str | os.PathLike | Capture | CaptureViews,
    library_path: str | os.PathLike | None,
    out_dir: str | os.PathLike,
    *,
    progress: ProgressFn | None = None,
    log: Log | None = None,
    overwrite: bool = False,
) -> Reconstruction:
    """Train `twin` again from its own record: its resolved configuration, seed, training views and registration
    (twin.json `config`, `training`, `choices.registration`), on the capture it was trained from."""
    if not twin.config or "views" not in twin.training:
        raise ValueError(f"{twin.root or 'the twin'} records no configuration to train again from (written by an older engine)")
    from reconstruction.library import load_library

    out = Path(out_dir)
    check_replaceable(out, overwrite)
    config = Preset.from_dict(twin.config)
    inputs = None if twin.training.get("inputs") is None else inputs_from_dict(twin.training["inputs"])
    init = "sphere" if twin.model_id == "sphere" else "cad"
    registration = None
    if init == "cad":
        if library_path is None:
            raise ValueError("--library is required to train a CAD-anchored twin again")
        library = load_library(library_path)
        capture = read_capture(capture) if isinstance(capture, (str, os.PathLike)) else capture
        registration = RegistrationResult.from_dict(
            twin.choices["registration"]["value"], library=library, where=f"{twin.root}'s registration"
        )
    seed = int(twin.training["seed"])
    prep = prepare(capture, library_path, indices=twin.training["views"], registration=registration, init=init, seed=seed, log=log)
    return _train_and_save(prep, config, inputs, out, seed=seed, progress=progress, overwrite=overwrite)

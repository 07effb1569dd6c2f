"""The pipeline's steps on one capture: register -> reconstruct -> export, each idempotent.

Both the local service and a Ray task run these same functions, so a cluster reproduces what one
machine computes. Every step writes its outputs atomically under the job's work directory and
returns a small JSON summary the job store keeps; a step whose outputs already exist (it finished
just before a crash, before the job store heard of it) returns them instead of redoing the work.

What a step computed flows forward instead of being recomputed: register writes the masks
(masks.npz) and the metric-aware registration (registration.json) that reconstruct and the fit
score use as given, and the images it decoded go on in memory (`Decoded`) to the same job's
reconstruct step, so a job decodes each image once.
"""

from __future__ import annotations

import io
import json
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from calibration.capture import Capture, read_capture
from calibration.fileio import MAX_IMAGE_PIXELS, atomic_write_bytes, atomic_write_json
from deploy.jobs import Job

if TYPE_CHECKING:
    from reconstruction.registration import RegistrationConfig
    from reconstruction.twin import Twin
    from reconstruction.views import CaptureViews
    from rig.config import RigConfig

Progress = Callable[[str, int, int], None]


def _default_registration() -> RegistrationConfig:
    from reconstruction.registration import RegistrationConfig

    return RegistrationConfig()


@dataclass(frozen=True)
class PipelineConfig:
    """What the service does with every capture. `registration`: rig.toml's [registration] (the known part, the
    scale tolerance, the photographs' tie-break), filled by whoever builds this from a rig.toml (service, kiosk)."""

    library: str
    preset: str = "cpu"
    export_formats: tuple[str, ...] = ("ply", "glb", "mjcf")
    seed: int = 0
    inspection_tolerance_mm: float | None = None  # set: every twin is inspected against its CAD (rig.toml [inspection])
    inspection_max_unseen_pct: float | None = None
    registration: RegistrationConfig = field(default_factory=_default_registration)
    max_image_pixels: int = MAX_IMAGE_PIXELS  # rig.toml [limits]: an image declaring more is refused undecoded


def pipeline_config(
    library: str | Path, preset: str = "cpu", *, rig: RigConfig | None = None, rig_toml: Path | None = None, **given
) -> PipelineConfig:
    """The one `PipelineConfig` of a line: rig.toml's [registration], [inspection] and [limits] (`rig`, as the caller
    parsed `rig_toml`), with what the caller states in `given` (command-line flags; None: rig.toml's value) over them."""
    stated = {k: v for k, v in given.items() if v is not None}
    if rig is not None:
        if rig.inspection is not None:
            stated.setdefault("inspection_tolerance_mm", rig.inspection.tolerance_mm)
            stated.setdefault("inspection_max_unseen_pct", rig.inspection.max_unseen_pct)
        stated.setdefault("registration", registration_config(rig_toml, loaded=rig))
        stated.setdefault("max_image_pixels", rig.max_image_pixels)
    return PipelineConfig(str(library), preset, **stated)


def registration_config(rig_toml: Path | None, *, loaded: RigConfig | None = None) -> RegistrationConfig:
    """rig.toml's [registration] as a RegistrationConfig (its defaults without a rig.toml); `loaded`: that file as the
    caller already parsed it. A bad file or key raises ConfigError / RegistrationError in one sentence naming it."""
    from reconstruction.registration import RegistrationConfig

    if rig_toml is None:
        return RegistrationConfig()
    if loaded is None:
        from rig.config import load_config

        loaded = load_config(rig_toml)
    return RegistrationConfig.from_dict(loaded.registration, where=f"{rig_toml}: registration")


REGISTRATION_JSON = "registration.json"
MASKS_NPZ = "masks.npz"


@dataclass
class Decoded:
    """A capture as one process decoded it: the register step leaves it here and the reconstruct step of
    the same job takes it, so each image file is decoded once per job (a resumed job decodes once more)."""

    capture_path: str = ""
    views: CaptureViews | None = None  # every view, undistorted, with its masks
    twin: Twin | None = None  # the twin the reconstruct step trained or read


def register_step(capture_path: Path, work: Path, cfg: PipelineConfig, decoded: Decoded | None = None) -> dict:
    """Masks and the metric-aware registration of the capture (`register_views` under `cfg.registration`), written to
    work/masks.npz and work/registration.json (with its provenance and the path taken: known part or library search),
    which the later steps read instead of redoing them."""
    out = work / REGISTRATION_JSON
    if out.exists() and (work / MASKS_NPZ).exists():
        return json.loads(out.read_text())["summary"]
    from reconstruction.library import load_library
    from reconstruction.registration import register_views, registration_document
    from reconstruction.views import capture_views

    capture = read_capture(capture_path, max_pixels=cfg.max_image_pixels)
    views = capture_views(capture)
    library = load_library(cfg.library)
    reg = register_views(views, library, cfg.registration, seed=cfg.seed)
    buf = io.BytesIO()
    np.savez_compressed(buf, masks=views.masks)
    atomic_write_bytes(work / MASKS_NPZ, buf.getvalue())
    summary = {"model_id": reg.model_id, "score": float(reg.score), "method": reg.method, "path": str(out)}
    # Written last: registration.json is what says the step is done.
    atomic_write_json(out, {"summary": summary, "registration": registration_document(reg, views, library, cfg.registration)})
    if decoded is not None:
        decoded.capture_path, decoded.views, decoded.twin = str(capture_path), views, None
    return summary


def fit_iou(twin: Twin, capture: Capture, masks: np.ndarray, renders: dict[str, np.ndarray] | None = None) -> float:
    """Mean silhouette IoU of the twin's renders of its training views against their masks ([V, H, W], one per capture view).
    renders: image name -> RGBA [H, W, 4] as the reconstruction made them; otherwise drawn here, in memory."""
    from reconstruction.gaussians import camera_batch, render
    from reconstruction.metrics import iou

    by_path = {f.file_path: i for i, f in enumerate(capture.frames)}
    scores = []
    for cam in twin.cameras:
        if renders is not None:
            alpha = renders[Path(cam.file_path).name][..., 3]
        else:
            alpha = render(twin.gaussians, *camera_batch(cam.camera), background=None)[1][0, ..., 0].numpy()
        scores.append(iou(alpha, masks[by_path[cam.file_path]]))
    return float(np.mean(scores))


def reconstruct_step(
    capture_path: Path, work: Path, cfg: PipelineConfig, progress: Progress | None = None, decoded: Decoded | None = None
) -> dict:
    """The twin of the capture from the register step's masks and registration (used as given) into work/twin. The views
    the register step decoded and the twin trained here stay in memory (`decoded`): nothing is decoded or loaded again."""
    from reconstruction.registration import RegistrationResult
    from reconstruction.twin import load_twin

    twin_dir = work / "twin"
    carried = decoded is not None and decoded.capture_path == str(capture_path) and decoded.views is not None
    if carried:
        views = replace(decoded.views, mask_source="given")  # masked by the register step, handed forward
        capture, masks = views.capture, views.masks
    else:
        with np.load(work / MASKS_NPZ) as npz:
            masks = npz["masks"]
        capture = read_capture(capture_path, max_pixels=cfg.max_image_pixels)
    renders = None
    if (twin_dir / "twin.json").exists():
        twin = load_twin(twin_dir)
    else:
        from reconstruction.library import load_library
        from reconstruction.pipeline import reconstruct_capture
        from reconstruction.views import capture_views

        reg = RegistrationResult.from_dict(
            json.loads((work / REGISTRATION_JSON).read_text())["registration"],
            capture=capture,
            library=load_library(cfg.library),
            where=str(work / REGISTRATION_JSON),
        )
        rec = reconstruct_capture(
            views if carried else capture_views(capture, masks=masks),
            cfg.library,
            twin_dir,
            registration=reg,
            preset=cfg.preset,
            seed=cfg.seed,
            progress=(lambda stage, i, n, _loss: progress(stage, i, n)) if progress else None,
        )
        twin, renders = rec.twin, rec.renders
    if decoded is not None:
        decoded.capture_path, decoded.views, decoded.twin = str(capture_path), None, twin
    summary = {
        "twin": str(twin_dir),
        "model_id": twin.model_id,
        "fit_iou": fit_iou(twin, capture, masks, renders),
        "total_s": float(twin.timings_s.get("total", 0.0)),
    }
    if cfg.inspection_tolerance_mm is not None:
        summary["inspection"] = inspect_step(work, cfg, twin)
    return summary


def inspect_step(work: Path, cfg: PipelineConfig, twin: Twin | None = None) -> dict:
    """`cadsplat inspect` of the job's twin into work/inspection (kept if already there): the verdict for the job record.
    `twin`: the job's twin as the reconstruct step holds it; read from work/twin otherwise."""
    from deploy.inspection_report import DEFAULT_MAX_UNSEEN_PCT, INSPECTION_JSON, inspect_twin_dir, write_inspection

    report = work / "inspection"
    if (report / INSPECTION_JSON).exists():
        doc = json.loads((report / INSPECTION_JSON).read_text())
    else:
        unseen = DEFAULT_MAX_UNSEEN_PCT if cfg.inspection_max_unseen_pct is None else cfg.inspection_max_unseen_pct
        settings = {"tolerance_mm": cfg.inspection_tolerance_mm, "max_unseen_pct": unseen, "turntable": 12}
        doc = (
            inspect_twin_dir(work / "twin", report, **settings)
            if twin is None
            else write_inspection(twin, report, twin_label=str(work / "twin"), **settings)
        )
    v = doc["verdict"]
    return {
        "status": v["status"],
        "line": v["line"],
        "exit_code": v["exit_code"],
        "part": v["part"],
        "deviation_mm": v["deviation_mm"],
        "at_mm": v["at_mm"],
        "unseen_pct": v["unseen_pct"],
        "out_of_view_pct": v.get("out_of_view_pct"),
        "tolerance_mm": v["tolerance_mm"],
        "report": str(report),
    }


def inspection_history(jobs: list[Job], model_id: str | None = None) -> dict[str, list[dict]]:
    """Finished jobs' inspection verdicts per part id (the CAD model a capture was registered to), oldest first."""
    out: dict[str, list[dict]] = {}
    for job in jobs:
        rec = job.steps["reconstruct"]
        if rec["status"] != "done" or "inspection" not in rec["output"]:
            continue
        part = rec["output"]["model_id"]
        if model_id is None or part == model_id:
            out.setdefault(part, []).append({"capture_id": job.capture_id, "finished": rec["finished"], **rec["output"]["inspection"]})
    return out


def export_step(work: Path, cfg: PipelineConfig, twin: Twin | None = None) -> dict:
    """The job's twin in each of `cfg.export_formats` under work/export (kept if already there). `twin`: the job's twin as
    the reconstruct step holds it; read and verified from work/twin otherwise."""
    from simulation.export import write_export

    twin_dir = work / "twin"
    outputs = {}
    for fmt in cfg.export_formats:
        target = work / "export" / (f"twin.{fmt}" if fmt in ("ply", "glb") else fmt)
        if not target.exists():
            target.parent.mkdir(parents=True, exist_ok=True)
            write_export(fmt, twin_dir, target, twin=twin)
        outputs[fmt] = str(target)
    return outputs


def make_step_runner(cfg: PipelineConfig, progress: Progress | None = None):
    """A `deploy.service.StepRunner` over the real engine."""

    decoded = Decoded()  # the images the register step decoded, for the same job's reconstruct step

    def run(step: str, job: Job, work_dir: Path, previous: dict[str, dict]) -> dict:
        capture = Path(job.capture_path)
        if step == "register":
            return register_step(capture, work_dir, cfg, decoded)
        if step == "reconstruct":
            return reconstruct_step(capture, work_dir, cfg, progress, decoded)
        if step == "export":
            held = decoded.twin if decoded.capture_path == str(capture) else None
            return export_step(work_dir, cfg, held)
        raise ValueError(f"unknown pipeline step {step!r}")

    return run


def process_capture(capture_path: str, work_dir: str, cfg: PipelineConfig) -> dict:
    """All steps of one capture in one call: what a Ray task runs."""
    import torch

    # One task per core: a worker's threads must not fight its neighbours'.
    torch.set_num_threads(1)
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    decoded = Decoded()
    reg = register_step(Path(capture_path), work, cfg, decoded)
    rec = reconstruct_step(Path(capture_path), work, cfg, decoded=decoded)
    exp = export_step(work, cfg, decoded.twin)
    return {"register": reg, "reconstruct": rec, "export": exp}

"""The pipeline's steps on one capture: register -> reconstruct -> export, each idempotent.

Both the local service and a Ray task run these same functions, so a cluster reproduces what one
machine computes. Every step writes its outputs atomically under the job's work directory and
returns a small JSON summary the job store keeps; a step whose outputs already exist (it finished
just before a crash, before the job store heard of it) returns them instead of redoing the work.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from calibration.capture import load_views, read_capture
from calibration.fileio import atomic_write_json
from deploy.jobs import Job

Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class PipelineConfig:
    library: str
    preset: str = "cpu"
    export_formats: tuple[str, ...] = ("ply", "glb", "mjcf")
    seed: int = 0
    inspection_tolerance_mm: float | None = None  # set: every twin is inspected against its CAD (rig.toml [inspection])
    inspection_max_unseen_pct: float | None = None


def register_step(capture_path: Path, work: Path, cfg: PipelineConfig) -> dict:
    out = work / "registration.json"
    if out.exists():
        return json.loads(out.read_text())["summary"]
    from reconstruction.library import load_library
    from reconstruction.masks import capture_masks
    from reconstruction.quality import check_masks, check_registration
    from reconstruction.registration import register

    capture = read_capture(capture_path)
    _, masks, cams = load_views(capture)
    if masks is None:
        masks, _ = capture_masks(capture)
    check_masks(masks, names=[f"view {i} ({f.camera_id})" for i, f in enumerate(capture.frames)])
    library = load_library(cfg.library)
    reg = register(masks, cams, library, seed=cfg.seed)
    check_registration(reg.score, reg.alternatives, masks, len(library.models), reg.model_id)
    summary = {"model_id": reg.model_id, "score": float(reg.score), "path": str(out)}
    atomic_write_json(out, {"summary": summary, "registration": reg.to_dict()})
    return summary


def fit_iou(twin_dir: Path, capture_path: Path) -> float:
    """Mean silhouette IoU of the twin's renders of its training views against their masks."""
    from PIL import Image

    from reconstruction.masks import capture_masks
    from reconstruction.metrics import iou
    from reconstruction.twin import load_twin

    twin = load_twin(twin_dir)
    capture = read_capture(capture_path)
    by_path = {f.file_path: i for i, f in enumerate(capture.frames)}
    masks = capture_masks(capture)[0] if not capture.has_masks else None
    scores = []
    for cam in twin.cameras:
        i = by_path[cam.file_path]
        render = np.asarray(Image.open(twin_dir / "renders" / f"{Path(cam.file_path).stem}.png"), np.float32) / 255.0
        mask = capture.mask(i) if masks is None else masks[i]
        scores.append(iou(render[..., 3], mask))
    return float(np.mean(scores))


def reconstruct_step(capture_path: Path, work: Path, cfg: PipelineConfig, model_id: str, progress: Progress | None = None) -> dict:
    twin_dir = work / "twin"
    if not (twin_dir / "twin.json").exists():
        from reconstruction.pipeline import reconstruct

        reconstruct(capture_path, cfg.library, twin_dir, preset=cfg.preset, model_id=model_id, seed=cfg.seed,
                    progress=(lambda stage, i, n, _loss: progress(stage, i, n)) if progress else None)
    doc = json.loads((twin_dir / "twin.json").read_text())
    summary = {
        "twin": str(twin_dir),
        "model_id": doc["model_id"],
        "fit_iou": fit_iou(twin_dir, capture_path),
        "total_s": float(doc.get("timings_s", {}).get("total", 0.0)),
    }
    if cfg.inspection_tolerance_mm is not None:
        summary["inspection"] = inspect_step(work, cfg)
    return summary


def inspect_step(work: Path, cfg: PipelineConfig) -> dict:
    """`cadsplat inspect` of the job's twin into work/inspection (kept if already there): the verdict for the job record."""
    from deploy.commands.inspect import DEFAULT_MAX_UNSEEN_PCT, INSPECTION_JSON, inspect_twin_dir

    report = work / "inspection"
    if (report / INSPECTION_JSON).exists():
        doc = json.loads((report / INSPECTION_JSON).read_text())
    else:
        unseen = DEFAULT_MAX_UNSEEN_PCT if cfg.inspection_max_unseen_pct is None else cfg.inspection_max_unseen_pct
        doc = inspect_twin_dir(work / "twin", report, tolerance_mm=cfg.inspection_tolerance_mm, max_unseen_pct=unseen, turntable=12)
    v = doc["verdict"]
    return {"status": v["status"], "line": v["line"], "exit_code": v["exit_code"], "part": v["part"], "deviation_mm": v["deviation_mm"],
            "at_mm": v["at_mm"], "unseen_pct": v["unseen_pct"], "tolerance_mm": v["tolerance_mm"], "report": str(report)}


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


def export_step(work: Path, cfg: PipelineConfig) -> dict:
    from simulation.export import write_export

    twin_dir = work / "twin"
    outputs = {}
    for fmt in cfg.export_formats:
        target = work / "export" / (f"twin.{fmt}" if fmt in ("ply", "glb") else fmt)
        if not target.exists():
            target.parent.mkdir(parents=True, exist_ok=True)
            write_export(fmt, twin_dir, target)
        outputs[fmt] = str(target)
    return outputs


def make_step_runner(cfg: PipelineConfig, progress: Progress | None = None):
    """A `deploy.service.StepRunner` over the real engine."""

    def run(step: str, job: Job, work_dir: Path, previous: dict[str, dict]) -> dict:
        capture = Path(job.capture_path)
        if step == "register":
            return register_step(capture, work_dir, cfg)
        if step == "reconstruct":
            return reconstruct_step(capture, work_dir, cfg, previous["register"]["model_id"], progress)
        if step == "export":
            return export_step(work_dir, cfg)
        raise ValueError(f"unknown pipeline step {step!r}")

    return run


def process_capture(capture_path: str, work_dir: str, cfg: PipelineConfig) -> dict:
    """All steps of one capture in one call: what a Ray task runs."""
    import torch

    # One task per core: a worker's threads must not fight its neighbours'.
    torch.set_num_threads(1)
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    reg = register_step(Path(capture_path), work, cfg)
    rec = reconstruct_step(Path(capture_path), work, cfg, reg["model_id"])
    exp = export_step(work, cfg)
    return {"register": reg, "reconstruct": rec, "export": exp}

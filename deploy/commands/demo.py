"""`cadsplat demo`: the bundled sample, end to end: validate it, build its CAD library, register,
reconstruct, render the held-out views and score them against the sample's ground truth."""

from __future__ import annotations

import json
import time
from pathlib import Path

import click
import cv2
import numpy as np

import deploy
from calibration.capture import Capture, read_capture
from calibration.fileio import sha256_file
from calibration.sim3 import Sim3

PLAUSIBLE_EXTENT_M = (0.002, 5.0)


class SampleError(ValueError):
    """A sample directory that is not what `benchmarks.bench_make_sample` writes; one sentence naming the file."""


def bundled_sample_dir() -> Path:
    """`sample/` at the repository root (the package is installed editable from the repository)."""
    return Path(deploy.__file__).resolve().parents[1] / "sample"


def mask_hit_fraction(vertices: np.ndarray, c2w_object: np.ndarray, capture: Capture, i: int) -> float:
    """Fraction of mesh vertices [N, 3] that view i's true pose projects inside its 1-px dilated mask (1.0 for an exact mask)."""
    cam = capture.camera(i).with_c2w(c2w_object)
    uv, depth = cam.project(vertices)
    mask = cv2.dilate(capture.mask(i).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    px = np.floor(np.nan_to_num(uv, nan=-1.0)).astype(int)
    inside = (depth > 0) & (px[:, 0] >= 0) & (px[:, 1] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] < cam.height)
    hit = np.zeros(len(vertices), bool)
    hit[inside] = mask[px[inside, 1], px[inside, 0]]
    return float(hit.mean())


def validate_sample(sample_dir: str | Path) -> dict:
    """Check a sample (captures, ground truth, CAD library) and return what it holds; raises SampleError.

    Checks: both captures read with every sha256 verified, masks and empty-rig backgrounds present,
    gt.json agrees with the captures (counts, sizes, rig->object Sim(3) maps the recorded poses onto
    the true object-frame poses), the true mesh projected with the true poses lands inside every
    mask, and each library mesh matches its digest, loads, and has a plausible size in metres.
    """
    root = Path(sample_dir)
    manifest = _read_json(root / "sample.json")
    gt = _read_json(root / manifest.get("gt", "gt.json"))
    captures = {name: _read_sample_capture(root / manifest.get(name, name)) for name in ("train", "heldout")}
    train, held = captures["train"], captures["heldout"]
    checks = [f"captures read, {sum(len(c.meta.get('sha256', {})) for c in captures.values())} sha256 digests verified"]
    sim3, deviation = _check_gt_poses(root / "gt.json", gt, train, held)
    checks.append(f"gt.json: rig->object Sim(3) (scale {sim3.scale:.3f}) maps recorded poses onto true poses within {deviation:.1e}")
    hits = _true_mesh_mask_hits(root, gt, train, held)
    checks.append(f"true mesh projected with true poses: {min(hits):.2%} of vertices inside every mask (1-px tolerance), {len(hits)} views")
    models = _check_library(root, manifest)
    checks.append(f"CAD library: {len(models)} meshes load with matching digests and sizes in metres")
    return {
        "sample_dir": str(root),
        "object": manifest.get("object", gt.get("mesh_name")),
        "true_model_id": manifest["true_model_id"],
        "views": len(train),
        "heldout": len(held),
        "size": gt.get("size"),
        "sim3_rig_to_object": sim3.to_dict(),
        "mask_hit_min": min(hits),
        "models": models,
        "checks": checks,
    }


def _read_sample_capture(path: Path) -> Capture:
    """The capture at path with every sha256 verified; SampleError unless every view has a mask and a background."""
    cap = read_capture(path, verify=True)
    if not cap.has_masks:
        raise SampleError(f"{cap.root}: some views have no mask")
    missing_bg = [f.camera_id for f in cap.frames if cap.meta.get("background", {}).get(f.camera_id) is None]
    if missing_bg:
        raise SampleError(f"{cap.root}: no empty-rig background for {', '.join(missing_bg[:3])}")
    return cap


def _check_gt_poses(gt_path: Path, gt: dict, train: Capture, held: Capture) -> tuple[Sim3, float]:
    """gt.json's rig->object Sim(3) and how far it maps the recorded poses from the true ones (max abs c2w entry).

    SampleError when the pose counts or image size disagree with the captures, or the map is off (the train poses
    may be off when gt.json records calibration noise).
    """
    for name, key, cap in (("train", "train_c2w_object", train), ("heldout", "heldout_c2w_object", held)):
        if len(gt.get(key, [])) != len(cap):
            raise SampleError(f"{gt_path}: {key} has {len(gt.get(key, []))} poses but {name} has {len(cap)} views")
    size = gt.get("size")
    if any([f.camera.width, f.camera.height] != size for c in (train, held) for f in c.frames):
        raise SampleError(f"{gt_path}: size {size} does not match the captures' image size")
    sim3 = Sim3.from_dict(gt["sim3_rig_to_object"])
    held_dev = np.abs(sim3.apply_to_c2w(np.stack([f.camera.c2w for f in held.frames])) - np.array(gt["heldout_c2w_object"])).max()
    train_dev = np.abs(sim3.apply_to_c2w(np.stack([f.camera.c2w for f in train.frames])) - np.array(gt["train_c2w_object"])).max()
    noisy = gt.get("calib_noise", {}).get("sigma_deg", 0) or gt.get("calib_noise", {}).get("sigma_mm", 0)
    if held_dev > 1e-6 or (not noisy and train_dev > 1e-6):
        raise SampleError(
            f"{gt_path}: sim3_rig_to_object does not map the recorded poses onto the true ones (off by {max(held_dev, train_dev):.2g})"
        )
    return sim3, max(held_dev, train_dev)


def _true_mesh_mask_hits(root: Path, gt: dict, train: Capture, held: Capture) -> list[float]:
    """Per view (train, then held-out), the fraction of the true mesh's vertices inside its mask; SampleError when any is short."""
    import trimesh

    mesh_path = root / gt["mesh"]
    if not mesh_path.is_file():
        raise SampleError(f"{root / 'gt.json'}: its mesh {mesh_path} is missing")
    vertices = np.asarray(trimesh.load(mesh_path, force="mesh", process=False).vertices, np.float64)
    hits = [
        mask_hit_fraction(vertices, np.array(c2w), cap, i)
        for key, cap in (("train_c2w_object", train), ("heldout_c2w_object", held))
        for i, c2w in enumerate(gt[key])
    ]
    if min(hits) < 0.999:
        raise SampleError(
            f"{mesh_path}: projected with the true poses, only {min(hits):.1%} of its vertices land inside the worst view's mask"
        )
    return hits


def _check_library(root: Path, manifest: dict) -> list[dict]:
    """Id, face count, largest extent and truth flag of each library mesh; SampleError when one is missing, altered,
    implausibly sized, or the true model is absent."""
    import trimesh

    digests = manifest.get("sha256", {})
    models = []
    for m in manifest.get("models", []):
        path = root / m["file"]
        if not path.is_file():
            raise SampleError(f"{path}: library mesh is missing")
        if m["file"] in digests and sha256_file(path) != digests[m["file"]]:
            raise SampleError(f"{path}: sha256 does not match sample.json (file changed or corrupt)")
        mesh = trimesh.load(path, force="mesh", process=False)
        extent = float(np.max(mesh.extents))
        if not PLAUSIBLE_EXTENT_M[0] <= extent <= PLAUSIBLE_EXTENT_M[1]:
            raise SampleError(f"{path}: largest extent {extent:.4g} m is implausible for a part in metres")
        models.append({"id": m["id"], "faces": len(mesh.faces), "extent_m": extent, "is_true_object": bool(m.get("is_true_object"))})
    if manifest.get("true_model_id") not in {m["id"] for m in models}:
        raise SampleError(f"{root / 'sample.json'}: the true model {manifest.get('true_model_id')} is not in the library")
    return models


def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise SampleError(f"{path}: missing; is this a cadsplat sample directory?")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise SampleError(f"{path}: invalid JSON ({e.msg} at line {e.lineno})") from None


def run_demo(root: Path, work: Path, *, preset: str = "cpu", heldout_views: int = 12, echo=click.echo) -> dict:
    """library -> register -> reconstruct -> render held-out views -> metrics against the sample's truth."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from deploy.commands.reconstruct import STAGE_TITLES
    from reconstruction.evaluation import run_protocol
    from reconstruction.library import build_library

    manifest = _read_json(root / "sample.json")
    gt = _read_json(root / manifest.get("gt", "gt.json"))
    timings: dict[str, float] = {}
    t = time.perf_counter()
    build_library(root / manifest.get("library_meshes", "library_meshes"), work / "library", progress=False, log=lambda _m: None)
    timings["library"] = time.perf_counter() - t
    tasks: dict[str, int] = {}
    with Progress(TextColumn("{task.description:<30}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()) as bar:

        def finish_stages() -> None:
            for task in tasks.values():
                bar.update(task, total=bar.tasks[task].completed)

        def progress(stage: str, it: int, cap: int, loss: float) -> None:
            if stage not in tasks:
                finish_stages()
                tasks[stage] = bar.add_task(STAGE_TITLES.get(stage, stage), total=cap)
            bar.update(tasks[stage], completed=it)

        def scoring(done: int, total: int) -> None:
            if done == 0:  # training is over: its bars stop where they ended (the display closes on leaving `with`)
                finish_stages()
                bar.live.stop()

        run = run_protocol(
            root / manifest.get("train", "train"),
            root / manifest.get("heldout", "heldout"),
            work / "library",
            work / "twin",
            preset=preset,
            heldout_views=heldout_views,
            refine_steps=0,
            gt=gt,
            progress=progress,
            log=lambda m: bar.console.print(f"  {m}"),
            heldout_progress=scoring,
        )
    timings |= run.timings_s
    return {
        "twin": run.twin,
        "registration": run.registration,
        "metrics": run.mean,
        "heldout_views": len(run.heldout_views),
        "reg_init": run.reg_init,
        "reg_refined": run.reg_refined,
        "timings_s": timings,
        "true_model_id": manifest["true_model_id"],
    }


@click.command(
    help="Run the bundled sample end to end: CAD library -> registration -> reconstruction (cpu preset) -> "
    "held-out renders -> fgPSNR, IoU and registration error against the sample's ground truth."
)
@click.option("--sample", "sample", type=click.Path(path_type=Path), default=None, help="Sample directory (default: the bundled sample/).")
@click.option("--preset", default="cpu", show_default=True, type=click.Choice(["cpu", "preview", "paper"]), help="Reconstruction preset.")
@click.option(
    "--work", "work", type=click.Path(path_type=Path), default=None, help="Keep the library and twin here (default: a temporary directory)."
)
@click.option("--validate-only", is_flag=True, help="Only check the sample and print what it holds.")
def demo(sample: Path | None, preset: str, work: Path | None, validate_only: bool) -> None:
    import shutil
    import tempfile

    root = sample or bundled_sample_dir()
    if not root.is_dir():
        raise click.ClickException(f"sample directory {root} does not exist")
    t0 = time.perf_counter()
    info = validate_sample(root)
    wall = time.perf_counter() - t0
    w, h = info["size"]
    click.echo(f"cadsplat demo: sample {info['object']} in {info['sample_dir']}")
    click.echo(f"  capture: {info['views']} train views + {info['heldout']} held-out views at {w}x{h}, masks and empty-rig backgrounds")
    names = ", ".join(m["id"] + (" (true)" if m["is_true_object"] else "") for m in info["models"])
    click.echo(f"  CAD library: {len(info['models'])} models: {names}")
    for line in info["checks"]:
        click.echo(f"  ok  {line}")
    click.echo(f"Sample valid ({wall:.1f} s).")
    if validate_only:
        return
    if work is not None and (work / "twin").exists():
        raise click.ClickException(f"{work / 'twin'} already exists; choose another --work directory")
    tmp = None
    if work is None:
        tmp = Path(tempfile.mkdtemp(prefix="cadsplat-demo-"))
        work = tmp
    work.mkdir(parents=True, exist_ok=True)
    from reconstruction.render.anchor import anchor_ms, ratio_line

    anchor = anchor_ms()  # read beside the run, so its wall time can be stated as a ratio that carries across machines
    try:
        r = run_demo(root, work, preset=preset)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    m, ri, rr, tw = r["metrics"], r["reg_init"], r["reg_refined"], r["timings_s"]
    found = r["twin"].model_id
    right = "the true model" if found == r["true_model_id"] else f"NOT the true model {r['true_model_id']}"
    fg = "n/a" if m.get("fgpsnr") is None else f"{m['fgpsnr']:.2f} dB"
    click.echo(f"Retrieved '{found}' ({right}); twin of {r['twin'].num_splats} splats, preset {preset}.")
    click.echo(f"Held-out views ({r['heldout_views']}): fgPSNR {fg}, IoU {m['iou']:.3f}, object-crop PSNR {m['psnr']:.2f} dB.")
    click.echo(
        f"Registration error (median over train cameras): {ri['rotation_deg_median']:.2f} deg / {ri['center_pct_median']:.2f} % "
        f"after retrieval, {rr['rotation_deg_median']:.2f} deg / {rr['center_pct_median']:.2f} % after reconstruction "
        f"(paper T_opt: 2.9 deg / 6.1 %)."
    )
    click.echo(
        f"Wall time: library {tw['library']:.0f} s, reconstruction {ratio_line(tw['reconstruct'], anchor)}, "
        f"evaluation {tw['evaluate']:.0f} s" + (f"; twin kept in {work / 'twin'}" if tmp is None else "") + "."
    )

"""`cadsplat register CAPTURE --library LIB --out reg.json`: best CAD model and rig-to-object Sim(3)."""

from __future__ import annotations

from pathlib import Path

import click


@click.command(help="Find the library model in CAPTURE and the Sim(3) from the rig frame to its CAD frame; writes reg.json.")
@click.argument("capture_dir", type=click.Path(path_type=Path))
@click.option("--library", "lib_dir", required=True, type=click.Path(path_type=Path), help="Library directory (cadsplat library build).")
@click.option("--out", "out_path", default="reg.json", show_default=True, type=click.Path(path_type=Path), help="Where to write the registration JSON.")
@click.option("--top-k", default=50, show_default=True, type=click.IntRange(1, 10000), help="Library views kept per mask.")
@click.option("--iou-threshold", default=0.7, show_default=True, type=click.FloatRange(0, 1), help="Minimum silhouette IoU of a kept view.")
@click.option("--model", "model_ids", multiple=True, help="Restrict the search to these model ids (repeatable).")
@click.option("--seed", default=0, show_default=True, type=int, help="RANSAC seed.")
def register(capture_dir: Path, lib_dir: Path, out_path: Path, top_k: int, iou_threshold: float, model_ids: tuple[str, ...], seed: int) -> None:
    import time

    from calibration.capture import read_capture
    from calibration.fileio import atomic_write_json
    from reconstruction.library import load_library
    from reconstruction.masks import capture_masks
    from reconstruction.quality import check_masks, check_registration
    from reconstruction.registration import register as run

    t0 = time.perf_counter()
    capture = read_capture(capture_dir)
    lib = load_library(lib_dir)
    masks, source = capture_masks(capture)
    check_masks(masks, names=[f"view {i} ({f.camera_id})" for i, f in enumerate(capture.frames)])
    t_masks = time.perf_counter() - t0
    cameras = [capture.camera(i) for i in range(len(capture))]
    res = run(masks, cameras, lib, top_k=top_k, iou_threshold=iou_threshold, seed=seed, model_ids=list(model_ids) or None)
    check_registration(res.score, res.alternatives, masks, len(lib.models), res.model_id)
    doc = res.to_dict()
    doc["timings_s"] = {"load_and_masks": round(t_masks, 4), **doc["timings_s"]}
    doc["mask_source"] = source
    doc["views"] = [f.file_path for f in capture.frames]
    if out_path.parent and not out_path.parent.exists():
        out_path.parent.mkdir(parents=True)
    atomic_write_json(out_path, doc)
    click.echo(f"{res.model_id}: mean IoU {res.score:.3f} over {len(cameras)} views (scale {res.sim3_rig_to_object.scale:.4g}), written to {out_path}")
    if res.ambiguity and res.ambiguity["ambiguous"]:
        click.echo(
            f"warning: a pose {res.ambiguity['rotation_deg']:.0f} degrees away scores within {res.ambiguity['score_gap']:.3f}; "
            "the object looks symmetric from these views", err=True,
        )

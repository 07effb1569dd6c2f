"""`cadsplat register CAPTURE --library LIB --out reg.json`: best CAD model, rig-to-object Sim(3), and the
object's pose in every camera (T_cam_obj with its uncertainty) plus an overlay PNG per photo.

Scale: a capture whose `cadsplat` block says `"units": "m"` (a metric calibration) has its scale
measured: the part must be within `--scale-tolerance` of its CAD size and reg.json says how far it
is off. Without units the scale is searched. The known part (`--known-part`, or rig.toml's
`[registration] known_part`) skips the library search; `--prior` (a previous reg.json) makes it the
fast conveyor search (yaw and position about the previous part's pose).

reg.json records its capture and library (`registration.provenance`), the config it was made with and
the path taken (`method`: library_search, known_part, known_part_prior), so `cadsplat reconstruct
--registration reg.json` uses it as given and refuses it for another capture or library. A fit below the
silhouette floor is refused in one sentence naming the views where the part lies outside its mask.
"""

from __future__ import annotations

from pathlib import Path

import click


@click.command(help="Find the library model in CAPTURE and the Sim(3) from the rig frame to its CAD frame; writes reg.json and overlays.")
@click.argument("capture_dir", type=click.Path(path_type=Path))
@click.option("--library", "lib_dir", required=True, type=click.Path(path_type=Path), help="Library directory (cadsplat library build).")
@click.option(
    "--out",
    "out_path",
    default="reg.json",
    show_default=True,
    type=click.Path(path_type=Path),
    help="Where to write the registration JSON.",
)
@click.option(
    "--overlays",
    "overlay_dir",
    default=None,
    type=click.Path(path_type=Path),
    help="Directory for the per-photo overlay PNGs (default: <out stem>_overlays beside --out).",
)
@click.option("--no-overlays", is_flag=True, help="Do not write overlay PNGs.")
@click.option("--top-k", default=None, type=click.IntRange(1, 10000), help="Library views kept per mask [default: rig.toml's, else 50].")
@click.option(
    "--iou-threshold",
    default=None,
    type=click.FloatRange(0, 1),
    help="Minimum silhouette IoU of a kept view [default: rig.toml's, else 0.7].",
)
@click.option("--model", "model_ids", multiple=True, help="Restrict the search to these model ids (repeatable).")
@click.option("--known-part", default=None, help="The library model every capture holds (no library search).")
@click.option(
    "--prior",
    "prior_path",
    default=None,
    type=click.Path(dir_okay=False, path_type=Path),
    help="A previous reg.json of the known part: its pose is the prior, the search is yaw + position on the conveyor.",
)
@click.option(
    "--rig-config",
    default=None,
    type=click.Path(dir_okay=False, path_type=Path),
    help="rig.toml: its [registration] table (known_part, scale_tolerance, prior, ...).",
)
@click.option(
    "--scale-tolerance",
    default=None,
    type=click.FloatRange(0, 0.99),
    help="Part size tolerance against its CAD model on a metric rig [default: rig.toml's, else 0.10].",
)
@click.option("--seed", default=0, show_default=True, type=int, help="RANSAC seed.")
def register(
    capture_dir: Path,
    lib_dir: Path,
    out_path: Path,
    overlay_dir: Path | None,
    no_overlays: bool,
    top_k: int | None,
    iou_threshold: float | None,
    model_ids: tuple[str, ...],
    known_part: str | None,
    prior_path: Path | None,
    rig_config: Path | None,
    scale_tolerance: float | None,
    seed: int,
) -> None:
    import time

    from calibration.capture import read_capture
    from calibration.fileio import atomic_write_json
    from reconstruction.library import load_library
    from reconstruction.registration import register_views, registration_document
    from reconstruction.views import capture_views

    t0 = time.perf_counter()
    cfg = config_from_options(
        rig_config, known_part=known_part, prior_path=prior_path, scale_tolerance=scale_tolerance, top_k=top_k, iou_threshold=iou_threshold
    )
    capture = read_capture(capture_dir)
    lib = load_library(lib_dir)
    views = capture_views(capture)  # decoded once: masks, the colour tie-break and the overlays
    t_views = time.perf_counter() - t0
    res = register_views(views, lib, cfg, model_id=list(model_ids) or None, seed=seed)
    doc = registration_document(res, views, lib, cfg)
    doc["timings_s"] = {"load_and_masks": round(t_views, 4), **doc["timings_s"]}
    if out_path.parent and not out_path.parent.exists():
        out_path.parent.mkdir(parents=True)
    if not no_overlays:
        doc["overlays"] = write_overlays(
            overlay_dir or out_path.parent / f"{out_path.stem}_overlays", views, lib.load_mesh(res.model_id), res.sim3_rig_to_object
        )
    atomic_write_json(out_path, doc)
    statement = res.scale_statement()
    click.echo(
        f"{res.model_id}: mean IoU {res.score:.3f} over {len(views)} views (scale {res.sim3_rig_to_object.scale:.4g}"
        + (f"; {statement}" if statement else "")
        + f"), written to {out_path}"
    )
    for tie in res.model_ties:
        click.echo(
            f"warning: {tie['model_id']} ({tie['cad_size_ratio']:.3g} times the size) fits within {tie['score_gap']:.3f}; "
            + ("a metric calibration would tell them apart" if views.metres_per_unit is None else "the masks cannot tell them apart"),
            err=True,
        )
    if res.ambiguity and res.ambiguity["ambiguous"]:
        click.echo(
            f"warning: a pose {res.ambiguity['rotation_deg']:.0f} degrees away scores within {abs(res.ambiguity['score_gap']):.3f}; "
            "the object looks symmetric from these views",
            err=True,
        )


def config_from_options(
    rig_config: Path | None,
    *,
    known_part: str | None = None,
    prior_path: Path | None = None,
    scale_tolerance: float | None = None,
    top_k: int | None = None,
    iou_threshold: float | None = None,
):
    """The `RegistrationConfig` of rig.toml's [registration] (when `rig_config` is given) with the command's options over it."""
    import dataclasses
    import json

    from deploy.steps import registration_config
    from reconstruction.registration import RegistrationConfig, RegistrationError
    from rig.config import ConfigError

    try:
        base = registration_config(rig_config)
    except (ConfigError, RegistrationError) as e:
        raise click.ClickException(str(e)) from None
    known_part = known_part or base.known_part
    if prior_path is not None and known_part is None:
        raise click.ClickException("--prior needs the known part (--known-part or rig.toml's [registration] known_part)")
    prior = base.prior if known_part == base.known_part else None
    if prior_path is not None:
        try:
            prior_doc = json.loads(prior_path.read_text())
            prior_model = prior_doc["model_id"]
            prior = RegistrationConfig.from_dict(
                {"known_part": prior_model, "prior": prior_doc["sim3_rig_to_object"]}, where=str(prior_path)
            ).prior
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise click.ClickException(f"{prior_path}: not a usable reg.json ({type(e).__name__}: {e})") from None
        if prior_model != known_part:
            raise click.ClickException(f"{prior_path}: registers {prior_model!r}, not the known part {known_part!r}")
    given = {"scale_tolerance": scale_tolerance, "top_k": top_k, "iou_threshold": iou_threshold}
    return dataclasses.replace(base, known_part=known_part, prior=prior, **{k: v for k, v in given.items() if v is not None})


def write_overlays(folder: Path, views, mesh, sim3) -> dict:
    """One overlay PNG per view into `folder`, published whole (built beside it, then swapped in, so a failure leaves
    the previous folder or none, never a half-written one); returns {view file: {"file", "sha256"}}."""
    import os
    import shutil

    import numpy as np

    from calibration.fileio import atomic_write_bytes, encode_png, publish_dir

    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = folder.parent / f".{folder.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    out = {}
    try:
        for k, (i, camera) in enumerate(zip(views.indices, views.cameras)):
            frame = views.capture.frames[i]
            img = overlay(views.images[k], views.masks[k], np.asarray(mesh.vertices), np.asarray(mesh.faces), camera, sim3)
            name = f"{Path(frame.file_path).stem}.png"
            out[frame.file_path] = {"file": str(folder / name), "sha256": atomic_write_bytes(tmp / name, encode_png(img))}
        publish_dir(tmp, folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def overlay(image, mask, vertices, faces, camera, sim3):
    """uint8 RGB [h, w, 3] (the `camera`'s own size) from a float photo [H, W, 3] and its bool mask [H, W], on a canvas at
    least the camera's size where views of mixed sizes sit top-left: the photo dimmed outside
    the registered CAD silhouette (mesh `vertices` [N, 3], `faces` [F, 3] under the rig-to-object
    `sim3`, seen by the rig `camera`), its outline in green, the observed mask's outline in magenta."""
    import cv2
    import numpy as np

    from reconstruction.registration import boundary
    from reconstruction.silhouette import render_silhouette

    image, mask = camera.crop(image), camera.crop(mask)
    cam_obj = camera.with_c2w(sim3.apply_to_c2w(camera.c2w))
    sil = render_silhouette(vertices, faces, cam_obj.K, cam_obj.viewmat, camera.width, camera.height)
    out = (np.clip(image[..., :3], 0, 1) * 255).astype(np.uint8)
    out[~sil] = (out[~sil] * 0.55).astype(np.uint8)
    thick = np.ones((2, 2), np.uint8)
    out[cv2.dilate(boundary(mask).astype(np.uint8), thick) > 0] = (255, 0, 255)
    out[cv2.dilate(boundary(sil).astype(np.uint8), thick) > 0] = (0, 255, 0)
    return out

"""`cadsplat calibrate`: board calibration, drift checks, history, printable boards."""

from __future__ import annotations

from pathlib import Path

import click

from calibration.board import BoardSpecError, board_image_at_dpi, detect_board, parse_board, to_gray_u8
from calibration.calibfile import CONVEYOR_FRAME, CalibrationFileError, CalibrationStore, from_rig
from calibration.capture import read_capture, read_image
from calibration.drift import CHEAP, THOROUGH
from calibration.fileio import atomic_write_bytes
from calibration.intrinsics import CalibrationError
from calibration.keeper import RECALIBRATE, Keeper, KeeperConfig, capture_images, plot_history
from calibration.multiview import calibrate_rig

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}


class RecalibrateAlarm(click.ClickException):
    """A camera drifted beyond correction: exit 3, so timers and scripts see it."""

    exit_code = 3


@click.group()
def calibrate() -> None:
    """The calibration keeper: board, sfm, check, history, board-image."""


def _spec(text: str):
    try:
        return parse_board(text)
    except BoardSpecError as e:
        raise click.ClickException(str(e)) from None


@calibrate.command("board-image")
@click.option("--board", "board", required=True, help="e.g. charuco:5x7:0.04:0.02:DICT_6X6_250 or chessboard:9x6:0.025")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True)
@click.option("--dpi", type=float, default=600.0, show_default=True, help="printer resolution; a square must be a whole number of pixels")
def board_image_cmd(board: str, out: Path, dpi: float) -> None:
    """Write a printable board PNG whose squares print at the spec's size at DPI."""
    import io

    from PIL import Image

    spec = _spec(board)
    try:
        img = board_image_at_dpi(spec, dpi)
    except BoardSpecError as e:
        raise click.ClickException(str(e)) from None
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG", dpi=(dpi, dpi))
    atomic_write_bytes(out, buf.getvalue())
    w, h = spec.size_m
    click.echo(f"{out}: {img.shape[1]}x{img.shape[0]} px, board {w * 1000:g} x {h * 1000:g} mm at {dpi:g} DPI (print at 100 %)")


def _image_folder(folder: Path) -> dict[str, Path]:
    if not folder.is_dir():
        raise click.ClickException(f"{folder} is not a folder of board images")
    files = {p.stem: p for p in sorted(folder.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES}
    if not files:
        raise click.ClickException(f"{folder} holds no images (.png, .jpg, ...)")
    return files


@calibrate.command("board")
@click.option("--board", "board", required=True, help="board spec, e.g. charuco:5x7:0.04:0.02:DICT_6X6_250")
@click.option(
    "--images",
    "folders",
    multiple=True,
    required=True,
    type=click.Path(path_type=Path),
    help="one folder per camera; frames matched by file name",
)
@click.option("--names", default=None, help="camera names, comma-separated (default: folder names)")
@click.option(
    "--out", type=click.Path(dir_okay=False, path_type=Path), required=True, help="calibration.json (new version; old ones are kept)"
)
@click.option(
    "--dist", "num_dist", type=click.Choice(["0", "4", "5"]), default="5", show_default=True, help="OpenCV distortion coefficients"
)
@click.option("--no-cross-validation", is_flag=True, help="skip the split-half uncertainty figures (faster)")
@click.option("--force", is_flag=True, help="store a calibration that fails the quality gate (RMS, intrinsics, coverage), marked as forced")
@click.option(
    "--conveyor-frame",
    default=None,
    help=f"the frame (image name) showing the board lying face up on the conveyor: the rig's up is measured from it "
    f"(default: the frame named '{CONVEYOR_FRAME}', when there is one)",
)
def board_cmd(
    board: str,
    folders: tuple[Path, ...],
    names: str | None,
    out: Path,
    num_dist: str,
    no_cross_validation: bool,
    force: bool,
    conveyor_frame: str | None,
) -> None:
    """Calibrate intrinsics and rig extrinsics from board images."""
    spec = _spec(board)
    cam_names = names.split(",") if names else [f.name for f in folders]
    if len(cam_names) != len(folders) or len(set(cam_names)) != len(cam_names):
        raise click.ClickException("give one distinct camera name per --images folder")
    detections, sizes = {}, {}
    with click.progressbar(list(zip(cam_names, folders)), label="detecting boards") as bar:
        for name, folder in bar:
            detections[name] = {}
            for stem, path in _image_folder(folder).items():
                img = to_gray_u8(read_image(path))
                h, w = img.shape
                if sizes.setdefault(name, (w, h)) != (w, h):
                    raise click.ClickException(
                        f"{path} is {w}x{h} but other images of camera '{name}' are {sizes[name][0]}x{sizes[name][1]}"
                    )
                detections[name][stem] = detect_board(spec, img)
    try:
        rig = calibrate_rig(detections, sizes, num_dist=int(num_dist), cross_validate=not no_cross_validation)
    except CalibrationError as e:
        raise click.ClickException(str(e)) from None
    try:
        doc = CalibrationStore(out).commit(from_rig(rig, board=str(spec), conveyor_frame=conveyor_frame), force=force)
    except CalibrationFileError as e:
        raise click.ClickException(str(e)) from None
    forced = f"; FORCED past the quality gate: {'; '.join(doc.notes['forced'])}" if doc.notes.get("forced") else ""
    click.echo(f"{out}: version {doc.version} ({len(rig.cameras)} cameras, rig frame = camera '{rig.reference}'){forced}")
    if doc.up_rig is not None:
        click.echo(f"  up (rig frame): {', '.join(f'{x:+.3f}' for x in doc.up_rig['vector'])}, from the {doc.up_rig['detail']}")
    for n in rig.cameras:
        k = rig.cameras[n].K
        cv = rig.intrinsics_cv_px[n]
        ex = (rig.extrinsics_cv or {}).get(n)
        line = f"  {n}: {len(rig.per_image_rms_px[n])} views, RMS {rig.rms_px[n]:.3f} px, fx {k[0, 0]:.1f} fy {k[1, 1]:.1f} cx {k[0, 2]:.1f} cy {k[1, 2]:.1f}, coverage {rig.coverage[n]:.0%}"
        line += f", cross-val {cv:.2f} px" if cv is not None else ""
        line += f", extrinsic cross-val {ex['rotation_deg']:.3f} deg / {ex['translation_mm']:.2f} mm" if ex and n != rig.reference else ""
        click.echo(line)
        if rig.outliers[n]:
            click.echo(f"    outlier views: {', '.join(rig.outliers[n])}")
        for view, why in rig.rejected[n].items():
            click.echo(f"    skipped {view}: {why}")


@calibrate.command("sfm")
@click.argument("capture", type=click.Path(path_type=Path))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True, help="calibration.json (new version)")
@click.option(
    "--reference",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="calibration to align to (default: the capture's own poses)",
)
@click.option("--max-error-px", type=float, default=1.0, show_default=True)
@click.option("--force", is_flag=True, help="store a calibration that fails the quality gate, marked as forced")
def sfm_cmd(capture: Path, out: Path, reference: Path | None, max_error_px: float, force: bool) -> None:
    """Board-free relative calibration of a capture with SfM (intrinsics held fixed)."""
    from calibration.calibfile import CalibrationDoc, read_calibration
    from calibration.sfm import sfm_calibrate

    cap = read_capture(capture)
    images = capture_images(cap)
    cams = {}
    for i, f in enumerate(cap.frames):
        cams.setdefault(f.camera_id, cap.camera(i))
    ref = {n: c.c2w for n, c in read_calibration(reference).cameras.items()} if reference else {n: c.c2w for n, c in cams.items()}
    res = sfm_calibrate(images, cams, reference=ref, max_reprojection_px=max_error_px)
    figures = {n: {"rms_px": res.reprojection_px} for n in res.cameras}
    notes = {
        "registered": f"{res.registered}/{res.total}",
        "points": res.points,
        "alignment_rms_m": res.alignment_rms_m,
        "capture": str(capture),
    }
    try:
        doc = CalibrationStore(out).commit(CalibrationDoc(res.cameras, figures, source="sfm", notes=notes), force=force)
    except CalibrationFileError as e:
        raise click.ClickException(str(e)) from None
    click.echo(
        f"{out}: version {doc.version}; registered {res.registered}/{res.total} images, reprojection {res.reprojection_px:.2f} px, "
        f"{res.points} points, aligned to the reference with {1000 * (res.alignment_rms_m or 0):.1f} mm RMS"
    )


def _latest_capture(folder: Path) -> Path:
    caps = [p for p in folder.iterdir() if (p / "transforms.json").exists()] if folder.is_dir() else []
    if not caps:
        raise click.ClickException(f"{folder} holds no captures (directories with transforms.json)")
    return max(caps, key=lambda p: (p / "transforms.json").stat().st_mtime)


def _keeper(calibration: Path, config: Path | None) -> Keeper:
    if not calibration.exists():
        raise click.ClickException(f"{calibration} does not exist; run 'cadsplat calibrate board' first")
    return Keeper(calibration, KeeperConfig.from_toml(config) if config else KeeperConfig())


@calibrate.command("check")
@click.argument("capture", required=False, type=click.Path(path_type=Path))
@click.option("--calibration", type=click.Path(dir_okay=False, path_type=Path), required=True)
@click.option("--latest", type=click.Path(file_okay=False, path_type=Path), default=None, help="check the newest capture in this folder")
@click.option("--thorough", is_flag=True, help="SIFT features and refined poses (the scheduled check)")
@click.option("--set-reference", is_flag=True, help="store the capture's empty-rig frames as the drift reference")
@click.option("--config", type=click.Path(dir_okay=False, path_type=Path), default=None, help="TOML with a [calibration.keeper] table")
def check_cmd(
    capture: Path | None, calibration: Path, latest: Path | None, thorough: bool, set_reference: bool, config: Path | None
) -> None:
    """Check every camera for drift; correct small drift, alarm on large (exit 3)."""
    if (capture is None) == (latest is None):
        raise click.ClickException("give either a CAPTURE or --latest FOLDER")
    path = capture if capture is not None else _latest_capture(latest)
    keeper = _keeper(calibration, config)
    cap = read_capture(path)
    if set_reference:
        frames = {cid: cap.background(cid) for cid in {f.camera_id for f in cap.frames}}
        frames = {k: v for k, v in frames.items() if v is not None} or capture_images(cap)
        click.echo(f"reference set for {', '.join(keeper.set_reference(frames))}")
        return
    rec = keeper.check(capture_images(cap), capture=str(path), mode=THOROUGH if thorough else CHEAP)
    for n, c in rec["cameras"].items():
        figs = "no reference visible" if c["effect_px"] is None else f"{c['rotation_deg']:.3f} deg, {c['effect_px']:.2f} px ({c['method']})"
        click.echo(f"  {n}: {c['status']}  {figs}")
    click.echo(f"{rec['status']}: {rec['action']}")
    alarm = keeper.alarm()
    if rec["status"] == RECALIBRATE or alarm is not None:
        raise RecalibrateAlarm(f"camera(s) {', '.join(alarm['cameras'])} drifted beyond correction; recalibrate the rig with a board")


@calibrate.command("history")
@click.option("--calibration", type=click.Path(dir_okay=False, path_type=Path), required=True)
@click.option("--plot", type=click.Path(dir_okay=False, path_type=Path), default=None, help="write a PNG of drift per camera over time")
@click.option("--config", type=click.Path(dir_okay=False, path_type=Path), default=None)
def history_cmd(calibration: Path, plot: Path | None, config: Path | None) -> None:
    """List calibration versions and drift checks."""
    keeper = _keeper(calibration, config)
    for v in keeper.store.versions():
        d = keeper.store.load(v)
        rms = ", ".join(f"{n} {f.get('rms_px'):.3f}" for n, f in d.figures.items() if f.get("rms_px") is not None)
        click.echo(f"v{v:04d}  {d.created}  {d.source:<16} parent {d.parent}  {('RMS px: ' + rms) if rms else ''}")
    records = keeper.history()
    for r in records:
        click.echo(f"check {r['check']:>4}  {r['time']}  {r['status']:<11} {r['action']}  {r['capture']}")
    alarm = keeper.alarm()
    if alarm:
        click.echo(
            f"ALARM since {alarm['since']}: recalibrate {', '.join(alarm['cameras'])}; {len(alarm['flagged_captures'])} captures flagged"
        )
    if plot is not None:
        plot_history(records, plot, keeper.config)
        click.echo(f"wrote {plot}")

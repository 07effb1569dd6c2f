"""`cadsplat reconstruct CAPTURE --library LIB --out TWIN`: capture -> registered, trained twin.

`--registration reg.json` (from `cadsplat register` of the same capture and library) skips registering.
`--like TWIN` trains a twin again from its own record (configuration, seed, views, registration).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

import click

if TYPE_CHECKING:
    from reconstruction.twin import Twin

T = TypeVar("T")

# Kept here so `--help` does not import torch; tests check them against presets.ABLATIONS and pose_correction.POSE_MODES.
ABLATION_NAMES = ("no-deformation", "no-pose", "no-mask-warmup", "no-sh-smoothness", "no-dropout")
POSE_MODE_NAMES = ("global", "per_camera")
STAGE_TITLES = {"pose": "Stage I: pose", "deform": "Stage I: pose + deformation", "photo": "Stage II: photometric"}


def parse_views(text: str | None) -> list[int] | None:
    """ "0,3,7" -> [0, 3, 7]; None -> None (all views)."""
    if text is None:
        return None
    try:
        out = [int(p) for p in text.split(",") if p.strip()]
    except ValueError:
        raise click.BadParameter(f"--views must be comma-separated view numbers like 0,3,7, got {text!r}") from None
    if not out or any(v < 0 for v in out) or len(set(out)) != len(out):
        raise click.BadParameter(f"--views must list distinct non-negative view numbers, got {text!r}")
    return out


def verdict(twin, registration) -> str:
    """One paragraph an operator can read: what was found, how well it fits, how long it took."""
    first = twin.losses.get("pose", {}).get("mask")
    last = twin.losses.get("photo", {}).get("mask")
    fit = f"silhouette error fell from {first:.3f} to {last:.3f}" if first is not None and last is not None else "training finished"
    delta = twin.sim3_rig_to_object_init.inverse() @ twin.sim3_rig_to_object
    rot = twin.sim3_rig_to_object_init.rotation_deg_to(twin.sim3_rig_to_object)
    skipped = twin.losses.get("skipped_nonfinite_steps", 0)
    warn = f" {skipped} training steps were skipped for non-finite values." if skipped else ""
    return (
        f"Twin of '{twin.model_id}' (registration IoU {registration.score:.3f}) with {twin.num_splats} splats, "
        f"SH degree {twin.gaussians.sh_degree}, preset {twin.preset}: {fit}; the pose correction turned the registration by "
        f"{rot:.2f} deg and rescaled it by {delta.scale:.4f}. Took {twin.timings_s.get('total', 0):.0f} s.{warn}"
    )


def given_registration(path: Path, capture_dir: Path, lib_dir: Path):
    """The capture and the registration in the reg.json at `path`, refused in one sentence when it is not
    one or was made from another capture or library."""
    import json

    from calibration.capture import read_capture
    from reconstruction.library import load_library
    from reconstruction.registration import RegistrationResult

    try:
        doc = json.loads(path.read_text())
    except OSError as e:
        raise click.ClickException(f"{path}: cannot read the registration ({e.strerror or e})") from None
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise click.ClickException(
            f"{path} is not a registration document (not JSON); give the reg.json `cadsplat register` wrote"
        ) from None
    capture = read_capture(capture_dir)
    return capture, RegistrationResult.from_dict(doc, capture=capture, library=load_library(lib_dir), where=str(path))


@click.command(help="Reconstruct a CAD-registered Gaussian-splat twin from CAPTURE; writes the twin directory OUT.")
@click.argument("capture_dir", type=click.Path(path_type=Path))
@click.option(
    "--library",
    "lib_dir",
    default=None,
    type=click.Path(path_type=Path),
    help="CAD library (cadsplat library build); not read with --init sphere.",
)
@click.option("--out", "out_dir", required=True, type=click.Path(path_type=Path), help="Twin directory to write.")
@click.option("--preset", default="cpu", show_default=True, type=click.Choice(["cpu", "preview", "paper"]), help="Model size and schedule.")
@click.option("--model", "model_id", default=None, help="Use this library model instead of retrieving one.")
@click.option(
    "--registration",
    "registration_path",
    default=None,
    type=click.Path(dir_okay=False, path_type=Path),
    help="A reg.json `cadsplat register` wrote for this capture and library: used as given instead of registering again.",
)
@click.option("--views", "views_text", default=None, help="Training views by index, e.g. 0,3,7 (default: all).")
@click.option(
    "--pose-mode",
    default=None,
    type=click.Choice(list(POSE_MODE_NAMES)),
    help="Override the pose-correction mode chosen from the capture's provenance.",
)
@click.option("--seed", default=0, show_default=True, type=int)
@click.option(
    "--init",
    "init",
    default="cad",
    show_default=True,
    type=click.Choice(["cad", "sphere"]),
    help="Anchor the splats on the registered CAD model, or on the paper's generic sphere (no CAD; for evaluation).",
)
@click.option(
    "--ablate",
    "ablations",
    multiple=True,
    type=click.Choice(list(ABLATION_NAMES)),
    help="Switch one ingredient off (repeatable), as the paper's ablations.",
)
@click.option(
    "--rig-config",
    default=None,
    type=click.Path(dir_okay=False, path_type=Path),
    help="rig.toml: its [registration] table (known_part, scale_tolerance, prior) when registering here.",
)
@click.option(
    "--like",
    "like_dir",
    default=None,
    type=click.Path(path_type=Path),
    help="Train again as the twin at this directory was trained: its configuration, seed, views and registration.",
)
@click.option("--overwrite", is_flag=True, help="Replace an existing twin at OUT.")
def reconstruct(
    capture_dir: Path,
    lib_dir: Path | None,
    out_dir: Path,
    preset: str,
    model_id: str | None,
    registration_path: Path | None,
    views_text: str | None,
    pose_mode: str | None,
    seed: int,
    init: str,
    ablations: tuple[str, ...],
    rig_config: Path | None,
    like_dir: Path | None,
    overwrite: bool,
) -> None:
    """Register and train the twin (or retrain one --like), with progress bars, and print its verdict."""
    from reconstruction.pipeline import reconstruct_capture, retrain_like

    views = parse_views(views_text)
    like = None
    if like_dir is not None:
        overrides = registration_path is not None or views is not None or model_id is not None or ablations or pose_mode is not None
        like = _load_like(like_dir, overrides=bool(overrides))
        init = "sphere" if like.model_id == "sphere" else "cad"
    if init == "cad" and lib_dir is None:
        raise click.UsageError("--library is required (or --init sphere to reconstruct without a CAD model)")
    _check_out_dir(out_dir, overwrite)
    from deploy.steps import registration_config

    reg_config = registration_config(rig_config)
    capture, registration = capture_dir, None
    if registration_path is not None:
        if init != "cad":
            raise click.UsageError("--registration places the CAD model; it does not go with --init sphere")
        capture, registration = given_registration(registration_path, capture_dir, lib_dir)
    if like is not None:
        train = functools.partial(retrain_like, like, capture, lib_dir, out_dir, overwrite=overwrite)
    else:
        train = functools.partial(
            reconstruct_capture,
            capture,
            lib_dir,
            out_dir,
            registration=registration,
            preset=preset,
            model_id=model_id,
            views=views,
            pose_mode=pose_mode,
            seed=seed,
            overwrite=overwrite,
            init=init,
            ablations=ablations,
            registration_config=reg_config,
        )
    result = _run_with_progress(train)
    click.echo(verdict(result.twin, result.registration))
    click.echo(f"Twin written to {out_dir}")


def _load_like(like_dir: Path, *, overrides: bool) -> Twin:
    """The twin at like_dir to train again; UsageError when options that its record fixes were also given."""
    from reconstruction.twin import load_twin

    if overrides:
        raise click.UsageError(
            "--like takes the configuration, views and registration from the twin's record; "
            "give it with CAPTURE, --library, --out and --overwrite only"
        )
    return load_twin(like_dir)


def _check_out_dir(out_dir: Path, overwrite: bool) -> None:
    """ClickException unless out_dir is free, or is a twin directory and --overwrite was given."""
    if out_dir.exists() and not overwrite:
        raise click.ClickException(f"{out_dir} already exists; choose another --out or pass --overwrite")
    from reconstruction.twin import is_twin_dir

    if out_dir.exists() and not is_twin_dir(out_dir):
        raise click.ClickException(
            f"{out_dir} is not a twin directory (no cadsplat twin.json), so --overwrite does not replace it; choose another --out"
        )


def _run_with_progress(train: Callable[..., T]) -> T:
    """train(progress=..., log=...)'s result, with one progress bar per training stage and log lines above them."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    tasks: dict[str, int] = {}
    with Progress(
        TextColumn("{task.description:<30}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("loss {task.fields[loss]:.4f}"),
        TimeElapsedColumn(),
        transient=False,
    ) as bar:

        def progress(stage: str, it: int, cap: int, loss: float) -> None:
            if stage not in tasks:
                for other in tasks.values():
                    bar.update(other, total=bar.tasks[other].completed)
                tasks[stage] = bar.add_task(STAGE_TITLES.get(stage, stage), total=cap, loss=float("nan"))
            bar.update(tasks[stage], completed=it, loss=loss)

        result = train(progress=progress, log=lambda m: bar.console.print(m))
        for t in tasks.values():
            bar.update(t, total=bar.tasks[t].completed)
    return result

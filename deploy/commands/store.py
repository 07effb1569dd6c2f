"""`cadsplat store verify | import-spill STORE`: every digest of a capture store checked; the spill emptied into it.

`verify` checks each committed capture against its transforms.json manifest, each quarantine entry
for its reason, each empty-rig reference version against its digests, that nothing was left
half-written and that no capture waits in the spill. Exit 0 when everything verifies, 1 otherwise.
It may run while the rig writes: what a live writer has in flight is counted, not reported as damage.

`import-spill` moves the captures the rig spilled (the store was unwritable until it stopped) into
the store under their ids, as the rig's next start does. It is a writer: while a rig holds the store
it is refused (naming the rig's pid), since the rig imports the spill itself when it starts and opening
the store would quarantine the capture the rig is writing.
"""

from __future__ import annotations

from pathlib import Path

import click

SPILL_HELP = "The rig's spill directory (default: storage.spill of --config, else $XDG_STATE_HOME/cadsplat/spill)."


def verify_store(root: Path, spill_dir: Path | None = None) -> tuple[dict, list[str]]:
    """(counts, problems): one sentence per capture, quarantine entry or reference that does not verify, and per
    capture still waiting in the spill (`spill_dir`, default rig.store.default_spill_dir()). Captures a running
    writer (the rig) has in flight are counted as `in_flight`, not as damage."""
    from calibration.capture import CaptureError, read_capture
    from rig.reference import ReferenceStore
    from rig.store import CAPTURES, INCOMING, QUARANTINE, REASON, REFERENCES, Spill, default_spill_dir, writer_holds

    problems: list[str] = []
    counts = {"captures": 0, "verified": 0, "quarantined": 0, "references": 0, "spilled": 0, "in_flight": 0}
    captures = sorted(p for p in (root / CAPTURES).iterdir() if p.is_dir()) if (root / CAPTURES).is_dir() else []
    for cap in captures:
        counts["captures"] += 1
        try:
            c = read_capture(cap, verify=True)
            if c.meta.get("capture_id") != cap.name:
                raise CaptureError(f"{cap}: its transforms.json names capture {c.meta.get('capture_id')!r}")
            if not set(c.meta.get("sha256", {})) >= {f.file_path for f in c.frames}:
                raise CaptureError(f"{cap}: the manifest does not cover every image")
            counts["verified"] += 1
        except (CaptureError, OSError, ValueError) as e:
            problems.append(str(e))
    for q in sorted((root / QUARANTINE).iterdir()) if (root / QUARANTINE).is_dir() else []:
        counts["quarantined"] += 1
        if not (q / REASON).is_file():
            problems.append(f"{q}: quarantined without a {REASON}")
    refs = ReferenceStore(root / REFERENCES)
    counts["references"] = len(refs.versions())
    problems += refs.verify()
    left = [p.name for p in (root / INCOMING).iterdir()] if (root / INCOMING).is_dir() else []
    # Listed before the writer is asked for: entries seen while a writer holds the store are its captures in flight
    # (it quarantined what an earlier crash left when it opened the store); with none, they are a crash's leftovers.
    if left and writer_holds(root):
        counts["in_flight"] = len(left)
    elif left:
        problems.append(f"{root / INCOMING}: {len(left)} half-written entries (opening the store moves them to quarantine)")
    for path, capture_id, _ in Spill(spill_dir or default_spill_dir(), root).entries():
        counts["spilled"] += 1
        problems.append(f"{path}: capture {capture_id} waits in the spill, not yet in the store (`cadsplat store import-spill {root}`)")
    return counts, problems


def _spill_dir(spill: Path | None, config: str | None) -> Path:
    from rig.config import ConfigError, load_config
    from rig.store import default_spill_dir

    if spill is not None:
        return spill
    if config is not None:
        try:
            return load_config(config).storage.spill or default_spill_dir()
        except ConfigError as e:
            raise click.ClickException(str(e)) from None
    return default_spill_dir()


def _require_store(root: Path) -> None:
    if not (root / "captures").is_dir():
        raise click.ClickException(f"{root} is not a capture store (no captures/ folder)")


@click.group()
def store() -> None:
    """The rig's capture store."""


_SPILL_OPTIONS = (
    click.option("--spill", type=click.Path(file_okay=False, path_type=Path), help=SPILL_HELP),
    click.option("--config", type=click.Path(dir_okay=False), help="rig.toml whose [storage] spill to use."),
)


def _spill_options(f):
    for opt in reversed(_SPILL_OPTIONS):
        f = opt(f)
    return f


@store.command()
@click.argument("root", type=click.Path(path_type=Path))
@_spill_options
def verify(root: Path, spill: Path | None, config: str | None) -> None:
    """Check every digest in the capture store ROOT and report (and any capture still waiting in the spill)."""
    _require_store(root)
    counts, problems = verify_store(root, _spill_dir(spill, config))
    for p in problems:
        click.echo(p)
    click.echo(
        f"{counts['verified']}/{counts['captures']} captures verify, {counts['quarantined']} quarantined, "
        f"{counts['references']} empty-rig reference version(s), {counts['spilled']} waiting in the spill"
        + (f", {counts['in_flight']} being written by the rig" if counts["in_flight"] else "")
        + f"; {len(problems)} problem(s)"
    )
    if problems:
        raise click.exceptions.Exit(1)


@store.command("import-spill")
@click.argument("root", type=click.Path(path_type=Path))
@_spill_options
def import_spill(root: Path, spill: Path | None, config: str | None) -> None:
    """Move the captures waiting in the spill into the capture store ROOT under their ids (with the rig stopped)."""
    from calibration.guard import LockHeld
    from rig.store import CaptureStore, Spill, lock_store

    _require_store(root)
    waiting = Spill(_spill_dir(spill, config), root)
    try:
        lock = lock_store(root, "store import-spill")
    except LockHeld as e:
        raise click.ClickException(f"{e}; a running rig imports the spill itself when it starts") from None
    except OSError as e:
        raise click.ClickException(f"cannot open the capture store {root} ({e.strerror or e})") from None
    try:
        try:
            store = CaptureStore(root, min_free_bytes=0)
        except OSError as e:
            raise click.ClickException(f"cannot open the capture store {root} ({e.strerror or e})") from None
        imported, problem = store.import_spill(waiting)
    finally:
        lock.release()
    for r in imported:
        click.echo(f"imported {r.capture_id}" + (f" into quarantine: {r.reason}" if r.status == "quarantined" else ""))
    click.echo(f"{len(imported)} capture(s) imported from {waiting.dir}")
    if problem:
        raise click.ClickException(problem)

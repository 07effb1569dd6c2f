"""`cadsplat store verify STORE`: every digest of a capture store checked, one line per problem.

Checks each committed capture against its transforms.json manifest, each quarantine entry for
its reason, each empty-rig reference version against its digests, and that nothing was left
half-written. Exit 0 when everything verifies, 1 otherwise.
"""

from __future__ import annotations

from pathlib import Path

import click


def verify_store(root: Path) -> tuple[dict, list[str]]:
    """(counts, problems): one sentence per capture, quarantine entry or reference that does not verify."""
    from calibration.capture import CaptureError, read_capture
    from rig.reference import ReferenceStore
    from rig.store import CAPTURES, INCOMING, QUARANTINE, REASON, REFERENCES

    problems: list[str] = []
    counts = {"captures": 0, "verified": 0, "quarantined": 0, "references": 0}
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
    if left:
        problems.append(f"{root / INCOMING}: {len(left)} half-written entries (opening the store moves them to quarantine)")
    return counts, problems


@click.group()
def store() -> None:
    """The rig's capture store."""


@store.command()
@click.argument("root", type=click.Path(path_type=Path))
def verify(root: Path) -> None:
    """Check every digest in the capture store ROOT and report."""
    if not (root / "captures").is_dir():
        raise click.ClickException(f"{root} is not a capture store (no captures/ folder)")
    counts, problems = verify_store(root)
    for p in problems:
        click.echo(p)
    click.echo(f"{counts['verified']}/{counts['captures']} captures verify, {counts['quarantined']} quarantined, "
               f"{counts['references']} empty-rig reference version(s); {len(problems)} problem(s)")
    if problems:
        raise click.exceptions.Exit(1)

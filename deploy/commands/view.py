"""`cadsplat view TWIN` / `cadsplat view --work WORK CAPTURE_ID`: the twin in a browser, read-only.

Serves the page (deploy/view.py) on a free port of 127.0.0.1 and prints its URL on stdout; the page draws the
splats with Spark (three.js), and toggles the deformed mesh, the CAD outline, the training cameras and the
inspection heat map with its verdict. `--host` binds another interface: the URL then carries a token the
server asks of every request. With `--work`, CAPTURE_ID names a job of the service (`cadsplat service run
--work WORK`) and its twin and inspection are served. Runs until Ctrl-C or SIGTERM.
"""

from __future__ import annotations

import signal
import threading
from pathlib import Path

import click

from calibration.guard import PathOutside, contained


def view_roots(target: str, work: Path | None):
    """The folders to serve for TARGET: a twin directory, or with `work` a service job's capture id."""
    from deploy.view import VENDOR_DIR, ViewRoots
    from reconstruction.twin import TWIN_JSON

    if work is not None:
        try:
            job = contained(work / "jobs", target, what="capture id")
        except PathOutside as e:
            raise click.ClickException(str(e)) from None
        twin, inspection = job / "twin", job / "inspection"
        if not (twin / TWIN_JSON).is_file():
            raise click.ClickException(f"job {target!r} under {work} has no finished twin ({twin / TWIN_JSON} is missing)")
    else:
        twin = Path(target)
        inspection = twin / "inspection"
        if not (twin / TWIN_JSON).is_file():
            raise click.ClickException(f"{twin} is not a twin (no {TWIN_JSON}); pass a twin directory, or --work and a capture id")
    if not (VENDOR_DIR / "@sparkjsdev/spark/dist/spark.module.js").is_file():
        raise click.ClickException(f"the page's renderer is not installed ({VENDOR_DIR} is empty): run `make env`")
    return ViewRoots(twin.resolve(), inspection.resolve() if inspection.is_dir() else None)


@click.command(
    help="Serve TWIN (a twin directory, or with --work a service job's capture id) as a page in the browser, "
    "read-only, and print its URL. Stops on Ctrl-C or SIGTERM."
)
@click.argument("target")
@click.option(
    "--work",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    default=None,
    help="The service's work folder: TARGET is then the capture id of one of its jobs.",
)
@click.option(
    "--host",
    default="127.0.0.1",
    show_default=True,
    help="Interface to bind. Anything but loopback makes the server ask for the token printed in the URL.",
)
@click.option("--port", default=0, type=click.IntRange(0, 65535), help="Port (default: a free one).")
def view(target: str, work: Path | None, host: str, port: int) -> None:
    from deploy.view import ViewServer, is_loopback, new_token, serve_until

    roots = view_roots(target, work)
    try:
        server = ViewServer(roots, host, port, None if is_loopback(host) else new_token())
    except OSError as e:
        raise click.ClickException(f"cannot listen on {host}:{port}: {e.strerror or e}") from None
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    click.echo(server.url())
    click.echo(f"  serving {roots.twin} read-only; Ctrl-C stops", err=True)
    serve_until(server, stop)

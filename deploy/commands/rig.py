"""`cadsplat rig list | capture | watch | reference`: the rig's cameras and triggers, from rig.toml or simulated.

`watch` prints one line per capture on stdout (`committed <id>`, `quarantined <id>: <reason>`,
...) only after the capture is durable, and a live status line on stderr. SIGTERM/SIGINT stop it
after the capture in flight. A full disk prints `STOPPED: disk full ...` once (the refused
triggers are counted on the status line) and `RESUMED ...` when space returns. A store that stays
read-only until the rig stops: its held captures go to the spill (`--spill`, `[storage] spill`)
and are imported into the store on the next start (`spilled <id>: ...`, then `imported <id>`).

One writer per store: each of these commands holds the store's lock (rig.store.lock_store) for its
life, so a second rig (or `store import-spill`) on the same store is refused naming the first's pid.

`reference` takes the empty-rig reference (the belt must be empty); the simulated rig takes one
itself on its first start, and `watch --reference-every S` retakes it on schedule.
"""

from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager
from pathlib import Path

import click

STORE_HELP = "Capture store directory (default: storage.root of the config)."
SPILL_HELP = (
    "Where captures wait when the store cannot be written until the rig stops; on another filesystem than the store "
    "(default: storage.spill of the config, else $XDG_STATE_HOME/cadsplat/spill)."
)


def _load(config: str | None, simulate: bool):
    from rig.config import ConfigError, load_config

    if simulate:
        return None
    if config is None:
        raise click.ClickException("give --config rig.toml, or --simulate to run on the synthetic rig")
    try:
        return load_config(config)
    except ConfigError as e:
        raise click.ClickException(str(e)) from None


@contextmanager
def _session(
    role: str,
    cfg,
    simulate: bool,
    store_dir: str | None,
    views: int,
    size: tuple[int, int],
    mesh: str | None,
    min_free_gb: float | None,
    spill_dir: str | None,
):
    """Take the store's writer lock (as `role`), open cameras and store (config or simulated), importing what waits in
    the spill; yields the acquisition. The lock is held until the acquisition is closed: opening the store quarantines
    what is left in its .incoming/ and continues its id counter, which only its one writer may do."""
    from calibration.guard import LockHeld
    from rig.store import lock_store

    if simulate and store_dir is None:
        raise click.ClickException("--simulate needs --store DIR (where the simulated captures go)")
    root = Path(store_dir) if store_dir else cfg.storage.root
    try:
        lock = lock_store(root, role)
    except LockHeld as e:
        raise click.ClickException(f"{e} (one writer per store)") from None
    except OSError as e:
        raise click.ClickException(f"cannot open the capture store {root} ({e.strerror or e})") from None
    try:
        with _opened(cfg, simulate, root, views, size, mesh, min_free_gb, spill_dir) as acq:
            yield acq
    finally:
        lock.release()


@contextmanager
def _opened(
    cfg, simulate: bool, root: Path, views: int, size: tuple[int, int], mesh: str | None, min_free_gb: float | None, spill_dir: str | None
):
    """Open cameras and the store at `root` (whose lock the caller holds); yields the acquisition."""
    from rig.acquisition import Acquisition, Thresholds, open_cameras
    from rig.assembly import build_cameras, build_store, load_rig_calibration, simulated_cameras
    from rig.camera import CameraError, CameraSettings
    from rig.store import CaptureStore, Spill, default_spill_dir

    synthetic = None
    if simulate:
        cameras, synthetic = simulated_cameras(views, size[0], size[1], Path(mesh) if mesh else None)
        store = CaptureStore(root, min_free_bytes=int((1.0 if min_free_gb is None else min_free_gb) * 1e9))
        rig_id, calibration_id, thresholds, settings = "simulated", "synthetic-ring", Thresholds(), CameraSettings(size[0], size[1])
        uncertainty, units, up_rig = None, "m", None
    else:
        from calibration.calibfile import CalibrationFileError, read_calibration
        from simulation.up import capture_up

        try:
            calibration_id, calibration, uncertainty = load_rig_calibration(cfg.calibration)
            calibration_doc = read_calibration(cfg.calibration) if cfg.calibration else None
            units = calibration_doc.units if calibration_doc else None
            up_rig = capture_up(calibration_doc.up_rig if calibration_doc else None, cfg.simulation.get("up"))
        except (CalibrationFileError, ValueError) as e:
            raise click.ClickException(f"the rig does not start: {e}") from None
        cameras = build_cameras(cfg, calibration)
        store = build_store(cfg, root)
        if min_free_gb is not None:
            store.min_free_bytes = int(min_free_gb * 1e9)
        rig_id, thresholds, settings = cfg.rig_id, cfg.thresholds, cfg.cameras[0].settings
    for r in store.recovered:
        click.echo(f"recovered {r.capture_id}: moved to quarantine ({r.reason})", err=True)
    spill = Spill(spill_dir or (cfg.storage.spill if cfg is not None and cfg.storage.spill else default_spill_dir()), store.root)
    imported, problem = store.import_spill(spill)
    for r in imported:
        click.echo(f"imported {r.capture_id} from the spill" + (f" into quarantine: {r.reason}" if r.status == "quarantined" else ""))
    if problem:
        click.echo(problem, err=True)
    try:
        locked = open_cameras(cameras, settings)
    except CameraError as e:
        for cam in cameras:
            cam.close()
        if synthetic is not None:
            synthetic.close()
        raise click.ClickException(str(e)) from None
    acq = Acquisition(
        cameras,
        store,
        rig_id=rig_id,
        calibration_id=calibration_id,
        calibration_uncertainty=uncertainty,
        units=units,
        up_rig=up_rig,
        thresholds=thresholds,
        settings=locked,
        spill=spill,
    )
    try:
        if acq.reference_note:
            click.echo(acq.reference_note, err=True)
        if not acq.backgrounds:
            if simulate:
                _report(acq.take_reference("first start of the simulated rig (its belt starts empty)"))
            else:
                click.echo(
                    "no empty-rig reference yet: captures carry no background, so the service cannot segment them; "
                    "run `cadsplat rig reference` with the belt empty",
                    err=True,
                )
        yield acq
    finally:
        for out in acq.close():  # what became of captures still held: committed now, spilled or failed
            _report(out)
        if synthetic is not None:
            synthetic.close()


def _report(out) -> None:
    if out.state_change == "resumed":
        click.echo("RESUMED: disk space is back; capturing again")
    if out.status == "committed":
        click.echo(f"committed {out.capture_id}  ({out.latency_ns / 1e6:.0f} ms after trigger {out.trigger.seq})")
    elif out.status in ("quarantined", "failed", "held", "spilled"):
        click.echo(f"{out.status} {out.capture_id}: {out.reason}")
    elif out.status == "reference":
        click.echo(f"reference {out.capture_id}: empty-rig frames taken ({out.reason})")
    elif out.status == "refused" and out.trigger.seq is not None and out.trigger.seq < 0:
        click.echo(f"refused {out.reason}")
    elif out.status == "refused" and out.reason.startswith("STOPPED"):
        if out.state_change == "stopped":  # once, not once per trigger; the status line counts the refusals
            click.echo(f"{out.reason} (trigger {out.trigger.seq} and those after it are refused before any frame is taken)")
    elif out.status in ("refused", "late"):
        click.echo(f"{out.status} trigger {out.trigger.seq}: {out.reason}")
    sys.stdout.flush()


def _status(acq, source) -> str:
    f, c = acq.trigger_filter, acq.counts
    free = acq.store.disk_free() / 1e9
    line = (
        f"triggers {f.received} | captures {c['committed']} | quarantined {c['quarantined']} | dropped {c['dropped']} "
        f"| missed {f.missed} | refused {c['refused']} | disk {free:.1f} GB free"
    )
    alarm = acq.stopped or acq.store.alarm or acq.camera_alarm or source.last_error
    return f"{line} | {alarm}" if alarm else line


def _common(f):
    for opt in reversed(
        [
            click.option("--config", "config", type=click.Path(dir_okay=False), help="rig.toml (cameras, trigger, storage, thresholds)."),
            click.option("--simulate", is_flag=True, help="Run on the synthetic rig (no hardware)."),
            click.option("--store", "store_dir", type=click.Path(file_okay=False), help=STORE_HELP),
            click.option("--views", default=8, show_default=True, type=click.IntRange(1, 64), help="Simulated cameras."),
            click.option(
                "--size",
                default=(640, 480),
                show_default=True,
                type=(click.IntRange(16, 4096), click.IntRange(16, 4096)),
                help="Simulated image size W H.",
            ),
            click.option(
                "--mesh",
                type=click.Path(exists=True, dir_okay=False),
                help="Simulated part (default: the bundled sample, else a procedural box).",
            ),
            click.option("--min-free-gb", type=click.FloatRange(0), help="Stop capturing below this much free disk."),
            click.option("--spill", "spill_dir", type=click.Path(file_okay=False), help=SPILL_HELP),
        ]
    ):
        f = opt(f)
    return f


@click.group()
def rig() -> None:
    """Camera drivers, triggers and captures from rig.toml (or --simulate)."""


@rig.command("list")
@click.option("--config", "config", type=click.Path(dir_okay=False), help="rig.toml whose cameras to list.")
def list_cmd(config: str | None) -> None:
    """Cameras: configured ones, OAK devices depthai can see (sockets, sensors, sync modes), and the synthetic rig."""
    from rig.assembly import DRIVERS
    from rig.camera import CameraError
    from rig.oak import describe_oak_device, import_depthai, list_oak_devices

    if config:
        cfg = _load(config, False)
        click.echo(f"rig {cfg.rig_id}: {len(cfg.cameras)} cameras, trigger {cfg.trigger.kind}, store {cfg.storage.root}")
        for c in cfg.cameras:
            where = c.device and f"{c.device} {c.socket}" or c.path or "test pattern"
            click.echo(f"  {c.id:<10} {c.driver:<8} {where}  {c.settings.width}x{c.settings.height} sync {c.settings.sync}")
    try:
        dai = import_depthai()
        devices = list_oak_devices(dai)
    except (CameraError, RuntimeError) as e:
        dai, devices = None, []
        click.echo(f"OAK devices: cannot enumerate ({e}).")
    if dai is not None and getattr(dai, "__name__", "") != "depthai":
        click.echo("OAK devices below come from a depthai fake, not from hardware.")
    if dai is not None and not devices:
        click.echo("OAK devices: none found (depthai sees no OAK on USB or the network).")
    elif devices:
        click.echo(f"OAK devices: {len(devices)} found")
    sockets: dict[str, set[str] | None] = {}
    for d in devices:
        try:
            info = describe_oak_device(d["device_id"], dai)
        except CameraError as e:
            sockets[d["device_id"]] = None
            click.echo(f"  {d['device_id']}  {d['platform']}  {d['state']}: {e}")
            continue
        sockets[d["device_id"]] = {sk["socket"] for sk in info["sockets"]}
        click.echo(f"  {d['device_id']}  {info['product']}  {info['platform']}  {len(info['sockets'])} sockets")
        for sk in info["sockets"]:
            click.echo(f"    {sk['socket']}  {sk['sensor']:<8} {sk['width']}x{sk['height']}  sync: {', '.join(sk['sync'])}")
    if config and dai is not None:
        for c in (c for c in cfg.cameras if c.driver == "oak"):
            if c.device not in sockets:
                click.echo(f"camera {c.id}: OAK {c.device} is not connected.")
            elif sockets[c.device] is not None and c.socket not in sockets[c.device]:
                click.echo(f"camera {c.id}: OAK {c.device} has no camera on {c.socket}.")
    click.echo(f"drivers: {', '.join(sorted(DRIVERS))} (synthetic: `--simulate`)")


@rig.command()
@_common
def capture(config, simulate, store_dir, views, size, mesh, min_free_gb, spill_dir) -> None:
    """Take one software-triggered capture."""
    from rig.triggers import SoftwareTrigger

    cfg = _load(config, simulate)
    with _session("rig capture", cfg, simulate, store_dir, views, size, mesh, min_free_gb, spill_dir) as acq:
        out = acq.handle(SoftwareTrigger().fire({"from": "cli"}))
        _report(out)
    if out.status != "committed":
        raise click.ClickException(f"the capture was not committed ({out.status}: {out.reason})")


@rig.command()
@_common
@click.option(
    "--trigger", "trigger_kind", type=click.Choice(["can", "serial"]), default="can", show_default=True, help="Simulated trigger line."
)
@click.option("--rate", default=0.5, show_default=True, type=click.FloatRange(0.01, 1000), help="Simulated triggers per second.")
@click.option("--max-captures", type=click.IntRange(1), help="Stop after this many captures (committed or quarantined).")
@click.option(
    "--reference-every",
    type=click.FloatRange(1),
    default=None,
    help="Retake the empty-rig reference every this many seconds while no trigger waits.",
)
def watch(
    config, simulate, store_dir, views, size, mesh, min_free_gb, spill_dir, trigger_kind, rate, max_captures, reference_every
) -> None:
    """Capture on every trigger until stopped, with a live status line."""
    from rig.assembly import SimulatedPlc, build_trigger

    cfg = _load(config, simulate)
    stop = threading.Event()
    with _session("rig watch", cfg, simulate, store_dir, views, size, mesh, min_free_gb, spill_dir) as acq:
        acq.reference_every_s = reference_every
        if simulate:
            plc = SimulatedPlc(trigger_kind, rate)
            source = plc.source
        else:
            plc, source = None, build_trigger(cfg.trigger)
            acq.trigger_filter.debounce_ns = int(cfg.trigger.debounce_ms * 1e6)
            acq.trigger_filter.min_interval_ns = int(cfg.trigger.min_interval_ms * 1e6)
        previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGTERM, signal.SIGINT)}
        tty = sys.stderr.isatty()
        show = lambda: click.echo(f"\r{_status(acq, source)}\033[K", nl=False, err=True) if tty else None  # noqa: E731
        try:
            plc.start() if plc else source.start()
            acq.run(source, stop, max_captures=max_captures, on_outcome=lambda o: (_report(o), show()), on_idle=show)
        finally:
            plc.stop() if plc else source.stop()
            for s, h in previous.items():
                signal.signal(s, h)
            pending = source.events.qsize()
            click.echo(
                ("\n" if tty else "") + _status(acq, source) + (f" | {pending} triggers unhandled at stop" if pending else ""), err=True
            )


@rig.command()
@_common
def reference(config, simulate, store_dir, views, size, mesh, min_free_gb, spill_dir) -> None:
    """Take the empty-rig reference now (the belt must be empty): a new version every capture records."""
    cfg = _load(config, simulate)
    with _session("rig reference", cfg, simulate, store_dir, views, size, mesh, min_free_gb, spill_dir) as acq:
        out = acq.take_reference("taken on command")
        _report(out)
    if out.status != "reference":
        raise click.ClickException(out.reason)

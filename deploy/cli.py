"""`cadsplat` command line. Sub-commands live in `deploy.commands.*` and are imported only when run,
so `cadsplat --help` stays fast (torch and friends load only for the command that needs them)."""

from __future__ import annotations

import importlib
import sys
from importlib.metadata import PackageNotFoundError, version

import click

from reconstruction.parallel import configure_openmp

# Before torch loads (sub-commands import it lazily): idle OpenMP threads spin only briefly, or on a small
# machine they steal the cores the rasterizer's threads need (benchmarks/results/rig_scenes.md).
configure_openmp()

# name -> (module:attribute, one-line help). The order is the order `--help` lists them in.
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("deploy.commands.demo:demo", "Bundled sample, end to end; prints the verdict."),
    "synth": ("deploy.commands.synth:synth", "Synthetic rig: train + held-out captures + gt.json from a mesh."),
    "library": ("deploy.commands.library:library", "Build and inspect a CAD library's silhouette index."),
    "register": ("deploy.commands.register:register", "Best CAD model + Sim(3) for a capture, per-view scores."),
    "reconstruct": ("deploy.commands.reconstruct:reconstruct", "Reconstruct a CAD-registered twin from a capture."),
    "evaluate": ("deploy.commands.evaluate:evaluate", "Paper-protocol metrics of a twin on held-out views."),
    "render": ("deploy.commands.render:render", "Render a twin from a capture's cameras or an orbit."),
    "inspect": ("deploy.commands.inspect:inspect", "Deviation from CAD: heat maps, CSV, PASS/FAIL/UNCERTAIN exit code."),
    "export": ("deploy.commands.export:export", "Export a twin as ply, glb, mjcf or colmap."),
    "view": ("deploy.commands.view:view", "The twin in a browser: a local read-only page (splats, meshes, cameras, heat map)."),
    "simulate": ("deploy.commands.simulate:simulate", "MuJoCo run of exported twins, rendered."),
    "rig": ("deploy.commands.rig:rig", "Camera drivers, triggers and captures from rig.toml."),
    "store": ("deploy.commands.store:store", "Verify every digest of a capture store."),
    "calibrate": ("deploy.commands.calibrate:calibrate", "The calibration keeper: board, sfm, check, history."),
    "kiosk": ("deploy.commands.kiosk:kiosk", "The operator screen."),
    "service": ("deploy.commands.service:service", "The pipeline service: captures -> twins, resumable."),
    "worker": ("deploy.commands.worker:worker", "Reconstruction on a Ray cluster."),
}


class LazyGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        target, short = COMMANDS[name]
        module, attr = target.split(":")
        try:
            cmd = getattr(importlib.import_module(module), attr)
        except ModuleNotFoundError as e:
            if e.name != module:
                raise
            raise click.ClickException(f"'cadsplat {name}' is not available in this build ({module} is missing)") from None
        cmd.short_help = cmd.short_help or short
        return cmd

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        # Help lists every command without importing any of them.
        with formatter.section("Commands"):
            formatter.write_dl([(name, short) for name, (_, short) in COMMANDS.items()])


def _version() -> str:
    try:
        return version("cadsplat")
    except PackageNotFoundError:
        return "unknown"


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(_version(), "--version", prog_name="cadsplat")
def cli() -> None:
    """cadsplat: CAD-registered Gaussian-splat digital twins from a calibrated multi-camera rig."""


def main(argv: list[str] | None = None) -> int:
    """Console entry point: bad input ends with one plain sentence on stderr and a non-zero exit."""
    try:
        # A command's own exit code (inspect's verdict) comes back as the return value.
        code = cli.main(args=argv, prog_name="cadsplat", standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("Aborted.", err=True)
        return 130
    except click.ClickException as e:
        e.show()
        return e.exit_code
    except click.exceptions.Exit as e:
        return e.exit_code
    except (ValueError, OSError, KeyError, RuntimeError) as e:
        # Domain errors carry one plain sentence (CaptureError, DegenerateError, ...).
        click.echo(f"Error: {e}", err=True)
        return 2
    return code if isinstance(code, int) else 0


if __name__ == "__main__":
    sys.exit(main())

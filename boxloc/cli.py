"""The ``boxloc`` command line: one group, thin verbs over library functions.

The algorithm's verbs live here. Verbs that record, replay or diff live in ``recorder`` and
``replay`` and are found through the ``boxloc.commands`` entry-point group, so this package
never imports them (the dependency points from recorder/replay to boxloc, not back).

Every user error ends in one line on stderr and exit code 2, never a traceback.
"""

from __future__ import annotations

import json
import sys
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

import click

from boxloc import __version__
from boxloc.errors import BoxlocError

EXIT_USAGE = 2


def _fail(msg: str) -> None:
    click.echo(f"boxloc: error: {msg}", err=True)
    sys.exit(EXIT_USAGE)


class _Group(click.Group):
    """A click group that turns project errors into one line and exit 2."""

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except BoxlocError as e:
            _fail(str(e).splitlines()[0] if str(e) else type(e).__name__)
        except (FileNotFoundError, IsADirectoryError, PermissionError) as e:
            _fail(f"{e.strerror}: {e.filename}")
        except OSError as e:
            if getattr(e, "errno", None) == 28:  # ENOSPC
                _fail(f"no space left on device: {e.filename or ''}".rstrip(": "))
            raise
        except KeyboardInterrupt:
            click.echo("boxloc: interrupted", err=True)
            sys.exit(130)

    def _load_plugins(self) -> None:
        if getattr(self, "_plugins_loaded", False):
            return
        self._plugins_loaded = True
        for ep in entry_points(group="boxloc.commands"):
            if ep.name in self.commands:
                continue
            try:
                cmd = ep.load()
            except ImportError as e:  # a broken optional verb must not break the others
                click.echo(f"boxloc: warning: command {ep.name!r} unavailable: {e}", err=True)
                continue
            self.add_command(cmd, ep.name)

    def list_commands(self, ctx: click.Context) -> list[str]:
        self._load_plugins()
        return super().list_commands(ctx)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        self._load_plugins()
        return super().get_command(ctx, name)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="boxloc")
def cli() -> None:
    """Find graspable surfaces of piled boxes in range scans (Katsoulas, DAGM 2003)."""


def config_options(f: Any) -> Any:
    """--config FILE and --set key=value, shared by every verb that runs the pipeline."""
    f = click.option(
        "--set", "overrides", multiple=True, metavar="KEY=VALUE",
        help="Override a config value (repeatable), e.g. --set alpha=0.05 --set noise.k2=0.001.",
    )(f)
    f = click.option(
        "--config", "config_path", type=click.Path(dir_okay=False), default=None,
        help="Config TOML file (see `boxloc config`).",
    )(f)
    return f


def load_config(config_path: str | None, overrides: tuple[str, ...], **extra: Any) -> Any:
    from boxloc.config import Config

    cfg = Config.load(config_path) if config_path else Config()
    if overrides:
        cfg = cfg.with_overrides(list(overrides))
    if extra:
        cfg = cfg.with_overrides({k: v for k, v in extra.items() if v is not None})
    return cfg


def scan_options(f: Any) -> Any:
    """Options that tell the readers how to turn an image into a scan."""
    f = click.option(
        "--depth-scale", type=float, default=None,
        help="Metres per depth unit for PNG/TIFF depth images (0.001 for millimetre PNGs).",
    )(f)
    f = click.option(
        "--intrinsics", default=None, metavar="FX,FY,CX,CY",
        help="Pinhole intrinsics, pixels, for depth images (and .npz without them).",
    )(f)
    return f


@cli.command()
@click.argument("scan_path", metavar="SCAN", type=click.Path(dir_okay=False))
@click.option("--output", "-o", type=click.Path(dir_okay=False), default=None,
              help="Write the JSON here instead of stdout.")
@click.option("--table", is_flag=True, help="Also print a table of the surfaces to stderr.")
@click.option("--workers", type=int, default=None, help="Processes for per-vertex work.")
@scan_options
@config_options
def locate(
    scan_path: str, output: str | None, table: bool, workers: int | None,
    intrinsics: str | None, depth_scale: float | None,
    config_path: str | None, overrides: tuple[str, ...],
) -> None:
    """Locate the graspable surfaces in one SCAN (.npz, .png, .tif, .pcd, .ply).

    Prints JSON: {"surfaces": [...], "timing_ms": {...}, "version": ...}; metres, sensor frame.
    """
    from boxloc.io import read_scan
    from boxloc.pipeline import find_graspable_surfaces

    cfg = load_config(config_path, overrides, workers=workers)
    scan = read_scan(scan_path, intrinsics=intrinsics, depth_scale=depth_scale)
    result = find_graspable_surfaces(scan, cfg)
    text = json.dumps(result.to_json(), indent=2)
    if output:
        Path(output).write_text(text + "\n")
    else:
        click.echo(text)
    if table:
        _print_surfaces(result)


def _print_surfaces(result: Any) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"{len(result.surfaces)} graspable surface(s)")
    for col in ("pick", "center x,y,z [m]", "width [mm]", "length [mm]", "normal", "score"):
        t.add_column(col, justify="right")
    s = result.surfaces
    for i in range(len(s)):
        t.add_row(
            str(int(s.pick_order[i])),
            ", ".join(f"{v:+.3f}" for v in s.centers[i]),
            f"{s.width[i] * 1e3:.1f}",
            f"{s.length[i] * 1e3:.1f}",
            ", ".join(f"{v:+.2f}" for v in s.normals[i]),
            f"{s.scores[i]:.3f}",
        )
    Console(stderr=True).print(t)
    ms = ", ".join(f"{k} {v:.0f}" for k, v in result.timing_ms.items())
    Console(stderr=True).print(f"time [ms]: {ms}")


@cli.command()
def config() -> None:
    """Print the default configuration as TOML (a starting point for --config)."""
    from boxloc.config import Config

    click.echo(Config().to_toml())


def main() -> None:
    """Console-script entry point."""
    cli(prog_name="boxloc")


if __name__ == "__main__":
    main()

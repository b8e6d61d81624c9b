"""The ``boxloc`` command line: one group, thin verbs over library functions.

The algorithm's verbs live here. Verbs that record, replay or diff live in ``recorder`` and
``replay`` and are found through the ``boxloc.commands`` entry-point group, so this package
never imports them (the dependency points from recorder/replay to boxloc, not back).

Every user error ends in one line on stderr and exit code 2, never a traceback.
"""

from __future__ import annotations

import json
import sys
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

    # Verbs from the boxloc.commands entry points load one at a time, when named: `boxloc
    # locate` and `boxloc --help` never import recorder, replay, rerun, mcap or dask.
    def _plugins(self) -> dict[str, Any]:
        """The boxloc.commands entry points not shadowed by a built-in verb, by name."""
        if not hasattr(self, "_entry_points"):
            from importlib.metadata import entry_points

            self._entry_points = {ep.name: ep for ep in entry_points(group="boxloc.commands")
                                  if ep.name not in self.commands}
        return self._entry_points

    def _load_plugin(self, name: str) -> click.Command | None:
        ep = self._plugins().get(name)
        if ep is None:
            return None
        try:
            cmd = ep.load()
        except ImportError as e:  # a broken optional verb must not break the others
            click.echo(f"boxloc: warning: command {name!r} unavailable: {e}", err=True)
            self._plugins().pop(name)
            return None
        self.add_command(cmd, name)
        return cmd

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted({*self.commands, *self._plugins()})

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        return self.commands.get(name) or self._load_plugin(name)

    def resolve_command(
        self, ctx: click.Context, args: list[str],
    ) -> tuple[str | None, click.Command | None, list[str]]:
        try:
            name, cmd, rest = super().resolve_command(ctx, args)
        except click.UsageError as e:  # "did you mean": among the plugins too (click >= 8.4)
            name = getattr(e, "command_name", None)
            if name is None:
                raise
            raise type(e)(name, possibilities=self.list_commands(ctx), ctx=ctx) from None  # type: ignore[call-arg]
        self.verb = name
        return name, cmd, rest

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """The verbs and their one-line help, without importing the plugins' modules."""
        commands: list[tuple[str, click.Command]] = []
        for n in self.list_commands(ctx):
            c = self.commands.get(n) or _described(self._plugins()[n], n)
            if c is not None and not c.hidden:
                commands.append((n, c))
        if commands:
            limit = formatter.width - 6 - max(len(n) for n, _ in commands)
            with formatter.section("Commands"):
                formatter.write_dl([(n, c.get_short_help_str(limit)) for n, c in commands])


def _described(ep: Any, name: str) -> click.Command | None:
    """A stand-in for an entry point's command carrying its docstring, read from the source.

    The help listing needs only each verb's first line; reading it with ``ast`` keeps
    rerun, mcap and dask (which the plugins' modules import) out of ``boxloc --help``.
    Falls back to loading the command when the source does not say plainly.
    """
    import ast
    import importlib.util

    module, _, attr = ep.value.partition(":")
    try:
        spec = importlib.util.find_spec(module)
        source = Path(spec.origin).read_text() if spec and spec.origin else ""
        for node in ast.parse(source).body:
            if isinstance(node, ast.FunctionDef) and node.name == attr and any(
                    "command" in ast.unparse(d) for d in node.decorator_list):
                return click.Command(name, help=ast.get_docstring(node))
    except (ImportError, OSError, SyntaxError, ValueError):
        pass
    try:
        cmd = ep.load()
    except ImportError:
        return None
    return cmd if isinstance(cmd, click.Command) else None


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
@click.argument("scan_path", metavar="SCAN", type=click.Path())  # the reader names the problem
@click.option("--output", "-o", type=click.Path(dir_okay=False), default=None,
              help="Write the JSON here instead of stdout.")
@click.option("--table", is_flag=True, help="Also print a table of the surfaces to stderr.")
@click.option("--workers", type=int, default=None, help="Processes for per-vertex work.")
@click.option("--box-sizes", "box_sizes", type=click.Path(dir_okay=False), default=None,
              metavar="FILE",
              help="The carton sizes the cell handles: a CSV with the header "
                   "width,length,height (metres; height may be empty). Flat regions that are "
                   "a multiple of a size are split; a box matching none is flagged.")
@scan_options
@config_options
def locate(
    scan_path: str, output: str | None, table: bool, workers: int | None,
    box_sizes: str | None, intrinsics: str | None, depth_scale: float | None,
    config_path: str | None, overrides: tuple[str, ...],
) -> None:
    """Locate the graspable surfaces in one SCAN (.npz, .png, .tif, .pcd, .ply).

    Prints JSON: {"surfaces": [...], "ambiguous": [...], "timing_ms": {...}, "version": ...};
    metres, sensor frame. "ambiguous" lists the flat regions the evidence cannot split into
    boxes (not graspable as they are).
    """
    from boxloc.io import read_scan

    cfg = load_config(config_path, overrides, workers=workers)
    if box_sizes is not None:
        import dataclasses

        from boxloc.io.box_sizes import read_box_sizes

        cfg = dataclasses.replace(cfg, box_sizes=read_box_sizes(box_sizes))
    # Read (and refuse bad input) before importing the pipeline: fast, clear failures.
    scan = read_scan(scan_path, intrinsics=intrinsics, depth_scale=depth_scale,
                     max_pixels=cfg.max_pixels)
    from boxloc.pipeline import find_graspable_surfaces

    result = find_graspable_surfaces(scan, cfg)
    from boxloc.stages.scan_noise import fit_warning

    if result.noise is not None and (w := fit_warning(result.noise)):
        click.echo(f"boxloc: warning: {w}", err=True)
    text = json.dumps(result.to_json(), indent=2)
    if output:
        Path(output).write_text(text + "\n")
    else:
        click.echo(text)
    if table:
        _print_surfaces(result)


def _print_surfaces(result: Any) -> None:
    import math

    from rich.console import Console
    from rich.table import Table

    from boxloc.products import AmbiguityReason, HeightSource

    t = Table(title=f"{len(result.surfaces)} graspable surface(s)")
    for col in ("pick", "center x,y,z [m]", "width [mm]", "length [mm]", "height [mm]",
                "normal", "score"):
        t.add_column(col, justify="right")
    s = result.surfaces
    for i in range(len(s)):
        h = (f"{s.height[i] * 1e3:.0f} ({HeightSource(int(s.height_source[i])).name.lower()})"
             if math.isfinite(float(s.height[i])) else "-")
        t.add_row(
            str(int(s.pick_order[i])),
            ", ".join(f"{v:+.3f}" for v in s.centers[i]),
            f"{s.width[i] * 1e3:.1f}",
            f"{s.length[i] * 1e3:.1f}",
            h + (" size unlisted" if s.sku_flagged[i] else ""),
            ", ".join(f"{v:+.2f}" for v in s.normals[i]),
            f"{s.scores[i]:.3f}",
        )
    Console(stderr=True).print(t)
    a = result.ambiguous
    for k in range(len(a)):
        reason = AmbiguityReason(int(a.reason[k])).name.lower()
        Console(stderr=True).print(
            f"ambiguous region {k}: {a.width[k] * 1e3:.0f} x {a.length[k] * 1e3:.0f} mm, "
            f"{reason} (not graspable as it is)")
    ms = ", ".join(f"{k} {v:.0f}" for k, v in result.timing_ms.items())
    Console(stderr=True).print(f"time [ms]: {ms}")


@cli.command()
@click.option("--n", "n", type=click.IntRange(min=1), default=None,
              help="Number of simulated scenes [default: 100; 320 with --matrix].")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the scene suite.")
@click.option("--out", type=click.Path(file_okay=False), default=None,
              help="Directory to write bench.json into.")
@click.option("--no-baseline", is_flag=True, help="Do not run the open3d baseline.")
@click.option("--replay", "replay_only", is_flag=True,
              help="Run only the replay section: `boxloc replay` throughput on 50 logs, "
                   "1 worker against 2 (from the replay package).")
@click.option("--fuzz", "fuzz_cases", type=click.IntRange(min=1), default=None, metavar="N",
              help="Run only the fuzz section with N cases (as --section fuzz --n N): bad "
                   "inputs to the scan and log readers; failing cases go to OUT/fuzz/failures.")
@click.option("--section", "sections", multiple=True, metavar="NAME",
              help="Run only these extra sections (repeatable): recording, replay, fuzz, …")
@click.option("--real", "real_dir", type=click.Path(), default=None, metavar="DIR",
              help="Benchmark on real labelled scans (organized PCD/PLY with a 'label' field, "
                   "e.g. mOSD) instead of simulated scenes; --out gets bench_real.json.")
@click.option("--frames", default=None, metavar="NAME,...",
              help="With --real: only these frames (file stems, comma-separated).")
@click.option("--noise", "noise_source", type=click.Choice(["auto", "estimate", "config"]),
              default="auto", show_default=True,
              help="With --real: the config as given (each scan's own model by default), a "
                   "model fitted to the scored frames and pinned, or the config's pinned.")
@click.option("--squareness", type=click.Choice(["cross", "estimate", "config"]),
              default="cross", show_default=True,
              help="With --real: angle_tolerance measured on the other frame groups, on all "
                   "the frames, or the config's.")
@click.option("--pose", type=click.Choice(["plane", "none"]), default="plane",
              show_default=True,
              help="With --real: sensor pose from each frame's dominant plane, or none.")
@click.option("--seeds", type=click.IntRange(min=1), default=None,
              help="Run each scene (or --real frame) N times, with trial_seed +0..N-1 (other "
                   "draws of the random trials); the figures pool them, each draw's is listed. "
                   "One draw is one sample of the trials' luck, and the default one is what "
                   "development was checked on. [default: 3]")
@click.option("--matrix", is_flag=True,
              help="The sensor x scene-kind matrix (boxloc.simulate.matrix_suite) with the "
                   "default configuration only (no --set, no --config; the box size range is "
                   "the simulator's); --out gets bench_matrix.json and bench_matrix.txt.")
@click.option("--packed", is_flag=True,
              help="Zero-gap, sharp-edged layered pallets for every sensor model of the zoo "
                   "(--n grid layers, then a third as many basket weaves, reported apart), "
                   "default configuration with and without the scenes' carton list "
                   "(boxloc.evaluate.packed_bench); --out gets bench_packed.json.")
@click.option("--bare", is_flag=True,
              help="Bare floors and pallets per sensor model of the zoo, default configuration: "
                   "false edges per pixel, scans with zero surfaces, each test's rejection rate "
                   "(boxloc.evaluate.bare_bench); --n is scenes per sensor; --out gets "
                   "bench_bare.json.")
@click.option("--jobs", type=click.IntRange(min=1), default=None,
              help="With --matrix: worker processes (results identical to one). [default: 1]")
@click.option("--held-out", "held_out", default=None, metavar="SENSOR",
              help="With --matrix: the sensor model kept out of development, reported "
                   "apart. [default: tof]")
@click.option("--scan-timeout", "scan_timeout", type=click.FloatRange(min=0, min_open=True),
              default=None, metavar="SECONDS",
              help="With --matrix: a scan still running after this long is killed and "
                   "counts as a failure. [default: 120]")
@click.option("--scene-set", "scene_sets", multiple=True, metavar="KEY=VALUE",
              help="Set a field of every simulated scene (repeatable; scene-spec keys, e.g. "
                   "noise.row_corr=0.276 for a sensor whose rows share part of their noise).")
@config_options
def bench(
    n: int | None, seed: int, out: str | None, no_baseline: bool, real_dir: str | None,
    frames: str | None, noise_source: str, squareness: str, pose: str,
    config_path: str | None, overrides: tuple[str, ...], replay_only: bool = False,
    sections: tuple[str, ...] = (), fuzz_cases: int | None = None,
    scene_sets: tuple[str, ...] = (), seeds: int | None = None, matrix: bool = False,
    jobs: int | None = None, held_out: str | None = None, scan_timeout: float | None = None,
    packed: bool = False, bare: bool = False,
) -> None:
    """Benchmark the localizer against the open3d baseline on N simulated scenes.

    Prints both side by side with the targets; with --out writes DIR/bench.json. Extra
    sections come from the `boxloc.bench` entry-point group (see boxloc.evaluate.scene_bench). With
    --real DIR, the real labelled scans of DIR instead (see boxloc.evaluate.real_bench). With
    --matrix, the sensor x scene-kind matrix, default configuration only (see
    boxloc.evaluate.matrix_bench). With --packed, zero-gap layered pallets per sensor model,
    with and without the carton list (see boxloc.evaluate.packed_bench). With --bare, bare
    floors and pallets per sensor model (see boxloc.evaluate.bare_bench).
    """
    import os

    # The time target is per core: pin the thread pools before the heavy imports read them.
    for var in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    matrix_only = {"jobs": jobs, "held-out": held_out, "scan-timeout": scan_timeout}
    chosen = [f for f, on in (("--matrix", matrix), ("--packed", packed), ("--bare", bare)) if on]
    if len(chosen) > 1:
        _fail(f"{' and '.join(chosen)} are separate benches: give one")
    if chosen:
        flag = chosen[0]
        not_with = {"config": config_path, "set": overrides, "scene-set": scene_sets,
                    "real": real_dir, "frames": frames, "section": sections,
                    "replay": replay_only, "fuzz": fuzz_cases}
        bad = [f"--{k}" for k, v in not_with.items() if v]
        ctx = click.get_current_context()
        bad += [f"--{k}" for k in ("noise", "squareness", "pose")
                if ctx.get_parameter_source(k if k != "noise" else "noise_source")
                is click.core.ParameterSource.COMMANDLINE]
        if bad:
            _fail(f"{flag} runs the default configuration only and its own scenes: "
                  f"{', '.join(bad)} cannot be used with it")
    if bare:
        if held_out is not None:
            _fail("--held-out does not apply with --bare (every sensor is reported apart)")
        if seeds is not None:
            _fail("--seeds does not apply with --bare (no random trials are pooled)")
        from boxloc.evaluate import bare_bench as bb

        bb.run_bare_bench(n or bb.DEFAULT_N, seed, out=Path(out) if out else None,
                          jobs=jobs or 1, scan_timeout=scan_timeout or bb.DEFAULT_SCAN_TIMEOUT,
                          progress=True)
        return
    if packed:
        from boxloc.evaluate import packed_bench as pb

        pb.run_packed_bench(n or pb.DEFAULT_N, seed, out=Path(out) if out else None,
                            jobs=jobs or 1, seeds=seeds or 3, held_out=held_out or pb.HELD_OUT,
                            scan_timeout=scan_timeout or pb.DEFAULT_SCAN_TIMEOUT)
        return
    if matrix:
        from boxloc.evaluate.matrix_bench import (
            DEFAULT_N,
            DEFAULT_SCAN_TIMEOUT,
            HELD_OUT,
            run_matrix_bench,
        )

        run_matrix_bench(n or DEFAULT_N, seed, out=Path(out) if out else None, jobs=jobs or 1,
                         seeds=seeds or 3, held_out=held_out or HELD_OUT,
                         scan_timeout=scan_timeout or DEFAULT_SCAN_TIMEOUT)
        return
    given = [f"--{k}" for k, v in matrix_only.items() if v is not None]
    if given:
        _fail(f"{', '.join(given)} only apply with --matrix, --packed or --bare")
    n = 100 if n is None else n
    seeds = 3 if seeds is None else seeds

    cfg = load_config(config_path, overrides)
    only = [*sections, *(["replay"] if replay_only else []),
            *(["fuzz"] if fuzz_cases and "fuzz" not in sections else [])]
    if only:  # selected by name: boxloc does not import replay or recorder
        from boxloc.evaluate.scene_bench import run_sections

        run_sections(only, fuzz_cases or n, seed, config=cfg, out=Path(out) if out else None)
        return
    if real_dir is not None:
        from boxloc.evaluate.real_bench import run_real_bench

        names = [f.strip() for f in frames.split(",") if f.strip()] if frames else None
        run_real_bench(real_dir, config=cfg, out=Path(out) if out else None,
                       baseline=not no_baseline, noise=noise_source, squareness=squareness,
                       pose=pose, frames=names, seeds=seeds)
        return
    from boxloc.evaluate.scene_bench import run_bench

    specs = None
    if scene_sets:
        from boxloc.simulate import override_spec, scene_suite

        specs = [override_spec(s, scene_sets) for s in scene_suite(n, seed)]
    run_bench(n, seed, config=cfg, out=Path(out) if out else None, baseline=not no_baseline,
              progress=True, specs=specs, seeds=seeds)


@cli.command()
def config() -> None:
    """Print the default configuration as TOML (a starting point for --config)."""
    from boxloc.config import Config

    click.echo(Config().to_toml())


@cli.command("calibrate-noise")
@click.argument("scan_paths", metavar="SCAN...", nargs=-1, required=True, type=click.Path())
@click.option("--output", "-o", type=click.Path(dir_okay=False), default=None,
              help="Also write the [noise] TOML table to this file.")
@click.option("--terms", default="sigma0,k1,k2", show_default=True,
              help="Model terms to fit (comma-separated subset of sigma0,k1,k2).")
@click.option("--estimator", type=click.Choice(["mad", "clipped"]), default="mad",
              show_default=True, help="Per-bin standard deviation: 1.4826*MAD or clipped std.")
@click.option("--incidence", type=click.Choice(["model", "ignore"]), default="model",
              show_default=True,
              help="'model': fit the NoiseModel's 1/cos(incidence) law; 'ignore': raw "
                   "along-ray scatter.")
@click.option("--bin-width", type=float, default=0.1, show_default=True,
              help="Width of the range bins, metres.")
@click.option("--use-labels", is_flag=True,
              help="Keep every plane fit inside one segment of a PCD's 'label' field.")
@scan_options
def calibrate_noise(
    scan_paths: tuple[str, ...], output: str | None, terms: str, estimator: str,
    incidence: str, bin_width: float, use_labels: bool,
    intrinsics: str | None, depth_scale: float | None,
) -> None:
    """Fit the range-noise model to flat surfaces in SCAN files (or directories of them).

    Measures the range noise against range and the share of it common to an image row
    (row_corr). Prints a TOML [noise] table (usable with --config) on stdout and the
    per-range-bin table on stderr.
    """
    from boxloc.calibrate.noise import estimate_noise, noise_toml
    from boxloc.errors import InputError
    from boxloc.io import read_labels, read_scans

    scans, labels = [], []
    for p in scan_paths:
        for scan in read_scans(p, intrinsics=intrinsics, depth_scale=depth_scale):
            scans.append(scan)
            lab = None
            if use_labels and Path(scan.source).suffix.lower() in (".pcd", ".ply"):
                try:
                    lab = read_labels(scan.source)
                except InputError:  # no label field: plain tiles
                    lab = None
            labels.append(lab)
    model, report = estimate_noise(
        scans, labels=labels, bin_width=bin_width, estimator=estimator, incidence=incidence,
        terms=[t.strip() for t in terms.split(",") if t.strip()],
    )
    text = noise_toml(model)
    click.echo(text, nl=False)
    if output:
        Path(output).write_text(text)
    _print_noise_report(report)


@cli.command("calibrate-angles")
@click.argument("scan_paths", metavar="SCAN...", nargs=-1, required=True, type=click.Path())
@scan_options
@config_options
def calibrate_angles(
    scan_paths: tuple[str, ...], intrinsics: str | None, depth_scale: float | None,
    config_path: str | None, overrides: tuple[str, ...],
) -> None:
    """Measure how square the sensor sees box corners: the prior angle_tolerance.

    Runs the edge, line and vertex stages on SCAN files (or directories) of boxes, with the
    config's noise model (calibrate that first), and takes the robust spread of the
    departures from 90 degrees of lines that meet at corners, less what their propagated
    error explains (see boxloc.calibrate.squareness). Prints `angle_tolerance = ...` (radians,
    usable in a --config TOML) on stdout and the figures on stderr.
    """
    import math

    from rich.console import Console

    from boxloc.calibrate.squareness import estimate_angle_tolerance

    cfg = load_config(config_path, overrides)
    tol, rep = estimate_angle_tolerance(_read_all(scan_paths, intrinsics, depth_scale), cfg)
    click.echo(f"angle_tolerance = {tol:.6g}  # {math.degrees(tol):.2f} deg")
    Console(stderr=True).print(
        f"{rep['n_scans']} scan(s): {rep['n_pairs']} line pairs meeting near their ends, "
        f"{rep['n_corners']} within {rep['critical']:.2f} sigma of square; spread "
        f"{rep['sigma_deg']:.2f} deg, propagated {rep['propagated_deg']:.2f} deg, "
        f"tolerance {rep['tolerance_deg']:.2f} deg")


@cli.command("calibrate-edges")
@click.argument("scan_paths", metavar="SCAN...", nargs=-1, required=True, type=click.Path())
@scan_options
@config_options
def calibrate_edges(
    scan_paths: tuple[str, ...], intrinsics: str | None, depth_scale: float | None,
    config_path: str | None, overrides: tuple[str, ...],
) -> None:
    """Measure how far the sensor blurs depth edges: the noise parameter edge_px.

    Runs the edge and line stages on SCAN files (or directories) of boxes, with the
    config's range-noise model (calibrate that first), and takes the robust spread of the
    edge points around their lines in pixels, less what their covariance explains (see
    boxloc.calibrate.edgeblur). Prints `edge_px = ...` (pixels; the [noise] table of a
    --config TOML, or --set noise.edge_px=...) on stdout and the figures on stderr.
    """
    from rich.console import Console

    from boxloc.calibrate.edgeblur import estimate_edge_px

    cfg = load_config(config_path, overrides)
    edge_px, rep = estimate_edge_px(_read_all(scan_paths, intrinsics, depth_scale), cfg)
    click.echo(f"edge_px = {edge_px:.4g}  # pixels, in [noise]")
    Console(stderr=True).print(
        f"{rep['n_scans']} scan(s): {rep['n_points']} edge points along lines, "
        f"{rep['n_kept']} within {rep['critical']:.2f} sigma; spread "
        f"{rep['spread_px']:.3f} px, modelled {rep['modelled_px']:.3f} px, "
        f"edge_px {rep['edge_px']:.3f} px")


def _read_all(paths: tuple[str, ...], intrinsics: str | None,
              depth_scale: float | None) -> list[Any]:
    """Every scan of the given files and directories, in order."""
    from boxloc.io import read_scans

    return [s for p in paths
            for s in read_scans(p, intrinsics=intrinsics, depth_scale=depth_scale)]


def _print_noise_report(report: dict[str, Any]) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"range noise: {report['n_scans']} scan(s), {report['n_tiles_used']} flat "
                    f"tiles, {report['n_points']} points ({report['estimator']}, incidence "
                    f"{report['incidence']})",
              caption="MAD, clip, model: std in mm (model at cos = 1); r: median range in m")
    # Both spreads are shown; the fit uses the estimator's. Model: at cos(incidence) = 1.
    for col in ("bin [m]", "r [m]", "points", "tiles", "MAD [mm]", "clip [mm]", "cos",
                "model [mm]", "fit"):
        t.add_column(col, justify="right", no_wrap=True)
    for row in report["rows"]:
        t.add_row(
            f"{row['lo']:.2f}-{row['hi']:.2f}", f"{row['range']:.3f}", str(row["count"]),
            str(row["tiles"]), f"{row['std_mad'] * 1e3:.3f}",
            f"{row['std_clipped'] * 1e3:.3f}", f"{row['mean_cos']:.2f}",
            f"{row['model_std'] * 1e3:.3f}", "yes" if row["used"] else "no",
        )
    con = Console(stderr=True)
    con.print(t)
    g = report.get("incidence_exponent")
    rej = ", ".join(f"{k} {v}" for k, v in report["tiles_rejected"].items() if v)
    con.print(f"fit: relative RMS {report['fit_rel_rms']:.3f}"
              + (f"; incidence exponent {g:.2f} (model assumes 1)" if g is not None else "")
              + (" [underdetermined: fewer bins than terms]" if report["underdetermined"]
                 else ""))
    rc = report.get("row_corr")
    if rc:
        con.print(f"row correlation {rc['value']:.3f} (share of the variance common to an "
                  f"image row; median {rc['median']:.3f} over {rc['tiles']} tiles, "
                  f"standard error {rc['std_error'] or 0:.3f})")
    co = report.get("correlation")
    if co:
        def lags(vals: list[float | None]) -> str:
            return ", ".join(f"{v:.2f}" if v is not None else "n/a" for v in vals)

        con.print(f"residual correlation at {', '.join(map(str, co['lags_px']))} px: along "
                  f"rows {lags(co['along_rows'])}; along columns {lags(co['along_columns'])}")
    tl = report.get("tails")
    if tl and tl["observed"]:
        con.print("beyond " + ", ".join(
            f"{k:g} sigma {o:.2e} (normal {n:.2e})"
            for k, o, n in zip(tl["sigmas"], tl["observed"], tl["normal"], strict=True))
            + f" of {tl['n_points']} residuals")
    con.print(f"tiles rejected: {rej or 'none'}")


@cli.command("simulate")
@click.argument("spec_text", metavar="KIND_OR_SPEC")
@click.option("--seed", type=int, default=None, help="Seed (overrides the spec's); with "
              "--count, the first of consecutive seeds.")
@click.option("--count", type=int, default=None, help="Write this many scans: PATH_stem_000.npz...")
@click.option("--out", "-o", "out", required=True, type=click.Path(),
              help="Output .npz file, or a directory for KIND_SEED.npz files.")
@click.option("--sensor", type=click.Choice(["laser", "tof", "structured-light",
                                             "active-stereo"]), default=None,
              help="A physical sensor model (boxloc.simulate.zoo) instead of the default "
                   "sensor (the localizer's noise model); overrides the spec's.")
def simulate_cmd(spec_text: str, seed: int | None, count: int | None, out: str,
                 sensor: str | None) -> None:
    """Simulate piled-box scans with exact ground truth (.npz with truth/...).

    KIND_OR_SPEC is a kind (single, pallet, partial, mixed, touching, empty, layered, floor)
    or a spec such as "mixed:seed=3,distance=2.0,bulge=0.01,sensor=tof". Prints one line per
    scan.
    """
    from boxloc.simulate import override_spec, parse_spec, simulate_to_files, summary_line

    spec = parse_spec(spec_text)
    if sensor is not None:
        spec = override_spec(spec, [f"sensor={sensor}"])
    for path, sim in simulate_to_files(spec, out, seed=seed, count=count):
        click.echo(summary_line(path, sim))


# Verbs that leave nothing to finalize once they return: no threads, no open recordings.
_QUICK_EXIT = frozenset({"locate", "simulate", "config", "calibrate-noise", "calibrate-edges",
                         "calibrate-angles"})


def main() -> None:
    """Console-script entry point.

    After a verb of ``_QUICK_EXIT`` the process ends without the interpreter's teardown of
    every module (scipy, numba, LLVM): 0.3-0.4 s of a `boxloc locate`, for nothing. The
    atexit handlers still run and stdout and stderr are flushed first; a failed flush
    exits 120, as the interpreter's own exit would.
    """
    try:
        cli(prog_name="boxloc")
    except SystemExit as e:
        import threading

        if getattr(cli, "verb", None) not in _QUICK_EXIT or threading.active_count() > 1:
            raise
        code = e.code
        if not isinstance(code, int):
            if code is not None:
                print(code, file=sys.stderr)
            code = 0 if code is None else 1
        _quick_exit(code)


def _quick_exit(code: int) -> None:
    """Run the atexit handlers, flush stdout and stderr, and end the process with CODE."""
    import atexit
    import os

    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe, a full disk: as Python's own exit
            code = code or 120
    os._exit(code)


if __name__ == "__main__":
    main()

"""``boxloc replay``: re-run the pipeline on the scans of stored logs, and diff.

Plugged into ``boxloc`` through the ``boxloc.commands`` entry-point group. Every user
error is a one-line :class:`BoxlocError` (exit code 2, printed by the ``boxloc`` group),
raised before any replay starts; problems with single logs are reported per log and the
other logs are still replayed.

Exit code: 0 every replayed log matches its input (identical, or within tolerances);
1 a regression; 2 an error (a log that cannot be read or replayed, a bad option).
"""

from __future__ import annotations

import functools
import json
import shlex
import sys
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import click

from boxloc.cli import config_options
from boxloc.errors import InputError
from recorder.commands import _RerunOption, normalize_rerun

EXIT_SAME, EXIT_REGRESSION, EXIT_ERROR = 0, 1, 2


def _load_config(config_path: str | None, overrides: tuple[str, ...]) -> Any:
    """The --config file (or None: each log's own config); overrides checked up front."""
    from boxloc.config import Config

    cfg = Config.load(config_path) if config_path else None
    if overrides:  # a typo must fail now, not once per log after the work
        (cfg or Config()).with_overrides(list(overrides))
    return cfg


def _echo(msg: str) -> None:
    click.echo(msg, err=True)


@click.command("replay")
@click.argument("logs", metavar="LOG_OR_DIR...", nargs=-1, required=True, type=click.Path())
@click.option("--out", "out", required=True, type=click.Path(file_okay=False),
              help="Directory for the new logs (one per input log; never overwritten).")
@click.option("--rev", "rev", default=None, metavar="GITREF",
              help="Replay another version of the code: a git revision, run from an isolated "
                   "worktree with the current environment.")
@click.option("--jobs", "-j", type=int, default=None,
              help="Local worker processes (default: all cores).")
@click.option("--scheduler", default=None, metavar="tcp://HOST:PORT",
              help="Run on an existing Dask distributed cluster (one task per log); its "
                   "workers must see the logs and --out at the same paths.")
@click.option("--tolerances", type=click.Path(dir_okay=False), default=None,
              help="Tolerances TOML for the diff against the input logs.")
@click.option("--rerun", "rerun", cls=_RerunOption, default="none", show_default=True,
              metavar="spawn|connect URL|save FILE.rrd|serve|none",
              help="Show an input log and its replay side by side in Rerun (the first "
                   "that differs).")
@click.option("--no-diff", is_flag=True, help="Only replay; do not diff against the inputs.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
@click.option("--box-sizes", "box_sizes", type=click.Path(dir_okay=False), default=None,
              metavar="FILE",
              help="Replay with this carton list instead of the recorded one: a CSV with the "
                   "header width,length,height (metres; height may be empty). Recorded in "
                   "the new logs' config and as their box_sizes.csv attachment.")
@config_options
def replay(logs: tuple[str, ...], out: str, rev: str | None, jobs: int | None,
           scheduler: str | None, tolerances: str | None, rerun: str, no_diff: bool,
           quiet: bool, box_sizes: str | None, config_path: str | None,
           overrides: tuple[str, ...]) -> None:
    """Re-run the pipeline on the scans stored in LOG_OR_DIR... and diff with the originals.

    Reads only the inputs of the original run (range images, sensor models, poses), runs
    the current code (or --rev GITREF) with each log's recorded config (or --config), plus
    --set overrides, and writes OUT/<log>.mcap, carrying its own version metadata. The
    input logs are never modified. Then prints the diff of each new log against its input.

    --box-sizes FILE replaces the carton list (like --set box_sizes=..., applied last); the
    diff then shows what the sizes changed. With --rev the revision runs with the same
    carton list (the log's, or --box-sizes), and the new logs keep the file; a revision
    that predates carton lists runs without them, which a warning says and the new log
    records.

    Exit code: 0 same or within tolerances, 1 regression, 2 error.
    """
    from replay.executors import default_jobs, run_dask, run_local
    from replay.replay import ReplayJob, collect_logs, plan_outputs, remove_partials
    from replay.versions import CURRENT, GitRevision, close_workers

    # Everything a user can get wrong fails here, before any work.
    rerun_target = normalize_rerun(rerun)
    if rerun_target != "none":
        from recorder.rerun.sink import parse_rerun_target

        parse_rerun_target(rerun_target)
    if jobs is not None and jobs < 1:
        raise InputError(f"--jobs must be >= 1, got {jobs}")
    if scheduler is not None and "://" not in scheduler:
        raise InputError(f"--scheduler must be an address like tcp://HOST:PORT, got "
                         f"{scheduler!r}")
    attachments = None
    if box_sizes is not None:
        from boxloc.io.box_sizes import read_box_sizes
        from recorder.mcap.sink import box_sizes_attachment
        from replay.replay import box_sizes_override

        # the file's sizes as the last override: they reach every executor and revision
        overrides = (*overrides, box_sizes_override(read_box_sizes(box_sizes)))
        attachments = box_sizes_attachment(box_sizes)
    paths = collect_logs(logs)
    out_dir = Path(out)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out_dir} is not a directory")
    names = plan_outputs(paths, out_dir)
    cfg = _load_config(config_path, overrides) if rev is None else None
    if rev is not None and config_path:
        from boxloc.config import Config

        cfg = Config.load(config_path)
    tol = _load_tolerances(tolerances) if not no_diff else None
    if rev is not None:
        GitRevision(rev).resolve()  # a missing ref is the quickest failure

    with ExitStack() as stack:
        version: Any = CURRENT
        if rev is not None:
            # checked out and checked (it imports) before any log is touched
            version = stack.enter_context(GitRevision(rev).prepare())
            _echo(f"replaying with {version.describe()}")
        out_dir.mkdir(parents=True, exist_ok=True)
        job = ReplayJob(out_dir=str(out_dir), config=cfg, overrides=tuple(overrides),
                        version=version, names={str(p): n for p, n in zip(paths, names)},
                        attachments=attachments)
        # leftovers of killed attempts, if any, even after an interrupt
        stack.callback(remove_partials, out_dir, names)
        t0 = time.perf_counter()
        if scheduler is not None:
            cleanup = None if rev is None else functools.partial(close_workers, version.root)
            outcomes = run_dask(paths, job, scheduler, progress=not quiet, cleanup=cleanup)
        else:
            outcomes = run_local(paths, job, jobs if jobs is not None else default_jobs(),
                                 progress=not quiet)
        elapsed = time.perf_counter() - t0
    _write_outcomes(out_dir / "replay.json", outcomes, rev, config_path, overrides, elapsed)
    code = _report_outcomes(outcomes, elapsed)
    diffs: list[Any] = []
    if not no_diff:
        diffs = _diff(outcomes, out_dir, tol, _bless_command(paths, names, out_dir))
        if diffs:
            from replay.report import exit_code

            code = max(code, int(exit_code(diffs, tol)))
    if rerun_target != "none":
        _side_by_side(outcomes, diffs, rerun_target, tol)
    sys.exit(code)


def _load_tolerances(path: str | None) -> Any:
    from replay.diff import load_tolerances

    return load_tolerances(path)


def _write_outcomes(path: Path, outcomes: list[Any], rev: str | None, config_path: str | None,
                    overrides: tuple[str, ...], elapsed: float) -> None:
    doc = {"rev": rev, "config": config_path, "overrides": list(overrides),
           "seconds": round(elapsed, 3), "logs": [o.to_dict() for o in outcomes]}
    path.write_text(json.dumps(doc, indent=1) + "\n")


def _report_outcomes(outcomes: list[Any], elapsed: float) -> int:
    """One line per log that needs one; the exit code of the replay itself (0 or 2)."""
    code = EXIT_SAME
    for o in outcomes:
        for w in o.warnings:
            _echo(f"warning: {w}")
        if o.error is not None:
            _echo(f"error: {o.error}")
            code = EXIT_ERROR
        for s in o.scans:
            if not s.ok:
                _echo(f"{o.input}: scan {s.index} failed: {s.error}")
    n_logs = sum(o.status == "ok" for o in outcomes)
    n_scans = sum(o.n_scans for o in outcomes)
    n_failed = sum(o.n_failed for o in outcomes)
    rate = n_logs / elapsed if elapsed > 0 else float("nan")
    _echo(f"replayed {n_logs}/{len(outcomes)} log(s), {n_scans} scan(s)"
          + (f" ({n_failed} failed)" if n_failed else "")
          + f" in {elapsed:.1f} s ({rate:.2f} logs/s)")
    return code


def _bless_command(paths: list[Path], names: list[str], out_dir: Path) -> str | None:
    """The command that makes the new logs the references (the inputs), when there is one."""
    if [p.name for p in paths] != names:
        return None
    if len(paths) == 1:
        return shlex.join(["boxloc", "diff", str(paths[0]), str(out_dir / names[0]),
                           "--update-refs", str(paths[0])])
    parents = {p.parent for p in paths}
    if len(parents) == 1:
        (d,) = parents
        return shlex.join(["boxloc", "diff", str(d), str(out_dir), "--update-refs", str(d)])
    return None


def _diff(outcomes: list[Any], out_dir: Path, tol: Any, bless: str | None) -> list[Any]:
    """Diff each new log against its input (:mod:`replay.diff`), print the table and write
    ``diff.jsonl`` / ``summary.json`` / ``report.html`` (:mod:`replay.report`) into
    ``out_dir``."""
    from boxloc.io.rosbag import is_rosbag
    from replay.diff import diff_logs
    from replay.report import print_table, write_outputs

    bags = [o for o in outcomes if o.output is not None and is_rosbag(o.input)]
    if bags:  # a bag holds scans only: there is nothing to diff the new log against
        _echo(f"{len(bags)} ROS 2 bag(s) replayed into new logs, not diffed (a bag has no "
              "products; diff those logs against later replays)")
    diffs = [diff_logs(o.input, o.output, tol) for o in outcomes
             if o.output is not None and o not in bags]
    if diffs:
        print_table(diffs, bless_command=bless)
        write_outputs(diffs, out_dir, title="boxloc replay")
    return diffs


def _side_by_side(outcomes: list[Any], diffs: list[Any], target: str, tol: Any) -> None:
    """Show one input log and its replay side by side in Rerun: the first pair that differs
    (else the first pair)."""
    from boxloc.io.rosbag import is_rosbag
    from replay.side_by_side import log_side_by_side

    pairs = [(o.input, o.output) for o in outcomes
             if o.output is not None and not is_rosbag(o.input)]
    if not pairs:
        _echo("--rerun: no log was replayed")
        return
    pick, ld = pairs[0], None
    for d in diffs:
        if d.error is None and not d.identical:
            pick, ld = (str(d.base), str(d.candidate)), d
            break
    if len(pairs) > 1:
        _echo(f"--rerun shows {Path(pick[0]).name} "
              + ("(the first log that differs)" if ld is not None else "(no log differs)"))
    serving = "serve" in target
    sink = log_side_by_side(pick[0], pick[1], target, ld, tolerances=tol, keep_open=serving)
    try:
        where = ", ".join(f"{k} {v}" for k, v in sink.urls.items() if k != "command")
        _echo(f"side by side -> {where or 'viewer'}")
        if serving and "web" in sink.urls:
            _echo(f"serving on 127.0.0.1; open {sink.urls['web']} (Ctrl-C stops)")
            while True:
                time.sleep(1.0)
    finally:
        sink.close()

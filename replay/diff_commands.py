"""``boxloc diff`` and ``boxloc explain``, plugged into ``boxloc`` (entry-point group
``boxloc.commands``).

``boxloc diff BASE CANDIDATE``: two logs, or two directories of logs matched by file name.
Prints the comparison, optionally writes ``diff.jsonl`` / ``summary.json`` / ``report.html``
(``--out DIR``), shows both runs side by side in Rerun (``--rerun ...``) and blesses the
candidate (``--update-refs REFS``). Exit code: 0 no regression, 1 regression, 2 error.

``boxloc explain LOG --scan N [--surface K | --failed-picks | --at X,Y] [--json]``: the
chain of decisions behind a surface, or where it stopped for a surface that was expected.

User errors are one line and exit code 2 (:class:`boxloc.errors.BoxlocError`, printed by
the ``boxloc`` group).
"""

from __future__ import annotations

import json
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import click

from boxloc.errors import InputError
from recorder.commands import _RerunOption, normalize_rerun

if TYPE_CHECKING:  # the diff machinery loads only when a command runs
    from replay.diff import LogDiff


def _pick_for_rerun(diffs: Sequence[LogDiff]) -> LogDiff | None:
    """The log pair to show side by side: the first with differences, else the first one."""
    ok = [d for d in diffs if d.error is None]
    for d in ok:
        if not d.identical:
            return d
    return ok[0] if ok else None


@click.command("diff")
@click.argument("base", metavar="BASE", type=click.Path())
@click.argument("candidate", metavar="CANDIDATE", type=click.Path())
@click.option("--tolerances", "tolerances_path", type=click.Path(dir_okay=False), default=None,
              help="Tolerances TOML overriding replay/tolerances.toml (any subset of keys).")
@click.option("--out", "out", type=click.Path(file_okay=False), default=None,
              help="Write diff.jsonl, summary.json and report.html into this directory.")
@click.option("--update-refs", "refs", type=click.Path(), default=None, metavar="REFS",
              help="Bless the candidate: copy its logs into REFS (a directory, or the "
                   "reference .mcap itself); replaced references go to REFS/.boxloc-bak/.")
@click.option("--rerun", "rerun", cls=_RerunOption, default="none", show_default=True,
              metavar="spawn|connect URL|save FILE.rrd|serve|none",
              help="Show baseline and candidate side by side in Rerun, differences marked.")
@click.option("--all-scans", is_flag=True, help="List identical scans in the table too.")
@click.option("--json", "as_json", is_flag=True,
              help="Print summary.json on stdout instead of the table.")
def diff(base: str, candidate: str, tolerances_path: str | None, out: str | None,
         refs: str | None, rerun: str, all_scans: bool, as_json: bool) -> None:
    """Compare BASE and CANDIDATE: two logs, or two directories of logs (by file name).

    Scans are matched by sequence (scan index); every stage is compared item by item within
    the tolerances; timing is shown on its own and never counts. Exit code: 0 no regression,
    1 regression, 2 error.
    """
    from rich.console import Console

    from replay.diff import diff_paths, load_tolerances
    from replay.report import EXIT_ERROR, bless, exit_code, print_table, summary, write_outputs

    rerun_target = normalize_rerun(rerun)
    if rerun_target != "none":
        from recorder.rerun.sink import parse_rerun_target

        parse_rerun_target(rerun_target)  # a bad target fails before any work
    tol = load_tolerances(tolerances_path)
    for p in (base, candidate):
        if not Path(p).exists():
            raise InputError(f"not found: {p}")
    diffs = diff_paths(base, candidate, tol)
    bless_cmd = shlex.join(["boxloc", "diff", base, candidate, "--update-refs", base])
    if as_json:
        click.echo(json.dumps(summary(diffs, tol), indent=2, sort_keys=True))
    else:
        print_table(diffs, Console(), bless_command=bless_cmd, all_scans=all_scans)
    if out:
        write_outputs(diffs, out)
        click.echo(f"boxloc diff: wrote {Path(out) / 'diff.jsonl'}, summary.json, report.html",
                   err=True)
    code = exit_code(diffs, tol)
    if rerun_target != "none":
        ld = _pick_for_rerun(diffs)
        if ld is None:
            click.echo("boxloc diff: --rerun: no pair of logs could be read", err=True)
        else:
            from replay.side_by_side import log_side_by_side

            if len(diffs) > 1:
                click.echo(f"boxloc diff: --rerun shows {ld.name} (the first log that "
                           "differs)", err=True)
            serving = "serve" in rerun_target
            sink = log_side_by_side(ld.base, ld.candidate, rerun_target, ld,
                                    keep_open=serving)
            try:
                where = ", ".join(f"{k} {v}" for k, v in sink.urls.items() if k != "command")
                click.echo(f"boxloc diff: side by side -> {where or 'viewer'}", err=True)
                if serving and "web" in sink.urls:
                    click.echo(f"serving on 127.0.0.1; open {sink.urls['web']} (Ctrl-C stops)",
                               err=True)
                    while True:
                        time.sleep(1.0)
            finally:
                sink.close()
    if refs:
        if code == EXIT_ERROR:
            raise InputError("refusing to bless: the runs could not be compared (see above)")
        written = bless(candidate, refs)
        click.echo(f"boxloc diff: blessed {len(written)} log(s) into {refs}: "
                   + ", ".join(str(p) for p in written), err=True)
        code = 0
    sys.exit(code)


@click.command("explain")
@click.argument("log_path", metavar="LOG.mcap", type=click.Path(dir_okay=False))
@click.option("--scan", "scan_index", type=click.IntRange(min=0), required=True,
              help="Scan index.")
@click.option("--surface", type=click.IntRange(min=0), default=None,
              help="Surface id (its row; 0 = first picked).")
@click.option("--failed-picks", is_flag=True,
              help="Explain every surface of the scan whose pick failed (boxloc annotate).")
@click.option("--at", "at", default=None, metavar="X,Y|X,Y,Z",
              help="Where a surface was expected: pixel X,Y (column, row) or a point X,Y,Z in "
                   "the sensor frame, metres (write --at=-0.1,0.2,1.5 for negatives).")
@click.option("--json", "as_json", is_flag=True, help="Print JSON for tools.")
def explain(log_path: str, scan_index: int, surface: int | None, failed_picks: bool,
            at: str | None, as_json: bool) -> None:
    """Print the chain of decisions for a surface of a recorded scan: its generating vertex
    and that vertex's lines, where its dimensions came from, every test with its statistic
    and critical value, the verification and the MDL competition. With --at, where the chain
    stopped for a surface that was expected there, and why. Without an option: every
    surface of the scan."""
    from replay.explain import explain as run_explain
    from replay.explain import format_explanation

    if not Path(log_path).is_file():
        raise InputError(f"log not found: {log_path}")
    d = run_explain(log_path, scan_index, surface=surface, at=at, failed_picks=failed_picks)
    if as_json:
        click.echo(json.dumps(d, indent=2, allow_nan=False))
    else:
        click.echo(format_explanation(d), nl=False)

"""Run the ``boxloc`` command line: in this process (quick), or in a subprocess as a user
would (bounded in time), for the few tests of the real exit code and stderr."""

from __future__ import annotations

import contextlib
import subprocess
import sys
from pathlib import Path

from click.testing import CliRunner

from boxloc.cli import cli

BOXLOC = [sys.executable, "-m", "boxloc.cli"]


def run(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """``python -m boxloc.cli ARGS`` in a subprocess."""
    return subprocess.run([*BOXLOC, *args], capture_output=True, text=True, timeout=300,
                          cwd=cwd)


def invoke(*args: str, cwd: Path | None = None,
           env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """The same command through click's test runner, in this process (in ``cwd``, with
    ``env`` added to the environment, both restored after).

    An exception the command line lets out (which a user would see as a traceback) is
    raised here, so the test fails with it.
    """
    with contextlib.chdir(cwd) if cwd is not None else contextlib.nullcontext():
        r = CliRunner(env=env).invoke(cli, list(args), prog_name="boxloc")
    if r.exception is not None and not isinstance(r.exception, SystemExit):
        raise r.exception
    return subprocess.CompletedProcess(["boxloc", *args], r.exit_code, r.stdout, r.stderr)

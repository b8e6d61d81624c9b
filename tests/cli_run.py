"""Run the ``boxloc`` command line in a subprocess, as a user would (bounded in time)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

BOXLOC = [sys.executable, "-m", "boxloc.cli"]


def run(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*BOXLOC, *args], capture_output=True, text=True, timeout=300,
                          cwd=cwd)

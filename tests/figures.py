"""Figures of the reliability tests, for docs/reliability.md.

With ``BOXLOC_FIGURES_DIR=DIR`` set, :func:`record` keeps ``{key: value}`` in
``DIR/<name>.json`` (merged across the tests of a run); without it, it does nothing.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any


def record(name: str, key: str, value: Any) -> None:
    d = os.environ.get("BOXLOC_FIGURES_DIR")
    if not d:
        return
    path = Path(d) / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    data = json.loads(path.read_text()) if path.is_file() else {}
    data[key] = value
    path.write_text(json.dumps(data, indent=1, sort_keys=True, default=str) + "\n")

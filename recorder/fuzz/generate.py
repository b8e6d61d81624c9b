"""One case's input from its category: the generator of each category.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from recorder.fuzz.bags import _gen_bag
from recorder.fuzz.cases import Case, Job
from recorder.fuzz.cloud_files import _gen_cloud
from recorder.fuzz.degenerate import _gen_pipeline, _gen_scan
from recorder.fuzz.image_files import _gen_image
from recorder.fuzz.log_bytes import _gen_log_bytes
from recorder.fuzz.log_records import _gen_log_records
from recorder.fuzz.npz_files import _gen_npz

_GENERATORS: dict[str, Callable[[np.random.Generator, dict[str, Any], Path], Job]] = {
    "log-bytes": _gen_log_bytes, "log-records": _gen_log_records, "npz": _gen_npz,
    "image": _gen_image, "cloud": _gen_cloud, "scan": _gen_scan, "pipeline": _gen_pipeline,
    "bag": _gen_bag,
}


def generate(case: Case, corpus: dict[str, Any], d: Path) -> Job:
    """Write the case's input files into ``d`` and return its steps (nothing is run)."""
    d.mkdir(parents=True, exist_ok=True)
    return _GENERATORS[case.category](case.rng(), corpus, d)

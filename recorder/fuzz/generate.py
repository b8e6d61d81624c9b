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


def write_cases(n: int, seed: int, out: Path, corpus: dict[str, Any]) -> list[dict[str, Any]]:
    """Write the inputs of cases ``0 .. n-1`` of a run seeded ``seed`` without running them.

    Each case's files go to ``out/case-NNNNN/`` (the ``scan`` and ``pipeline`` cases have
    none: their inputs are arrays); ``out/cases.json`` lists the cases.

    Parameters
    ----------
    n : int
        Number of cases (they cycle through the categories as in a run).
    seed : int
        The run's seed.
    out : Path
        Where to write; created.
    corpus : dict
        The inputs to mutate (:func:`recorder.fuzz.corpus.corpus_at`).

    Returns
    -------
    list of dict
        One row per case: ``case``, ``category``, ``kind``, ``read_kw`` and ``files``
        (``{name: sha256 hex}``), so that two runs' cases compare byte for byte.

    Notes
    -----
    A case is a function of ``(seed, index)`` and the corpus alone: neither the order in
    which cases run, nor which ones a worker ran before, nor ``PYTHONHASHSEED`` change its
    bytes (``tests/test_fuzz_determinism.py``).
    """
    import hashlib
    import json

    from recorder.fuzz.cases import plan

    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in plan(n, seed):
        d = out / f"case-{case.index:05d}"
        job = generate(case, corpus, d)
        files = {str(f.relative_to(d)): hashlib.sha256(f.read_bytes()).hexdigest()
                 for f in sorted(d.rglob("*")) if f.is_file()}
        rows.append({"case": case.index, "category": case.category, "kind": job.kind,
                     "read_kw": job.read_kw, "files": files})
    (out / "cases.json").write_text(json.dumps(rows, indent=1, default=str) + "\n")
    return rows

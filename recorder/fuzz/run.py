"""A fuzz run: the corpus, the cases in worker processes, and the report.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from recorder.fuzz.cases import (
    _MAX_LISTED,
    CATEGORIES,
    DEFAULT_MEM_BOUND_MB,
    DEFAULT_TIMEOUT_S,
    plan,
)
from recorder.fuzz.corpus import build_corpus, default_sample_logs
from recorder.fuzz.pool import _Pool


def run_fuzz(
    n: int,
    seed: int = 0,
    *,
    sample_logs: Sequence[str | os.PathLike[str]] | None = None,
    workdir: str | os.PathLike[str] | None = None,
    workers: int = 2,
    timeout_s: float = DEFAULT_TIMEOUT_S,
    mem_bound_mb: float = DEFAULT_MEM_BOUND_MB,
    progress: bool = False,
) -> dict[str, Any]:
    """Run ``n`` fuzz cases and report them.

    Parameters
    ----------
    n : int
        Number of cases (they cycle through :data:`CATEGORIES`).
    seed : int
        Seeds every case (case ``i`` uses ``default_rng([seed, i])``).
    sample_logs : paths, optional
        Logs to mutate besides the small ones made here; default the repository's
        ``logs/*.mcap``.
    workdir : path, optional
        Where the corpus, the workers' scratch space and the failing cases go
        (``failures/case-NNNNN/``). Default: a temporary directory, removed after a run
        without failures.
    workers : int
        Worker processes.
    timeout_s : float
        Per-case wall-time limit, seconds.
    mem_bound_mb : float
        Per-case bound on peak resident-memory growth, MB.
    progress : bool
        Print a line to stderr every 500 cases.

    Returns
    -------
    dict
        ``cases``, ``outcomes`` (ok / error / failure counts), ``by_category``,
        ``failure_kinds``, ``failures`` (the first :data:`_MAX_LISTED`), ``top_errors``,
        ``seconds``, ``cases_per_s``, the limits and where the failures were saved.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        from boxloc.errors import InputError

        raise InputError(f"the number of fuzz cases must be an integer >= 0, got {n!r}")
    keep = workdir is not None
    # absolute: the workers change into their own scratch directories
    wd = (Path(workdir) if workdir is not None
          else Path(tempfile.mkdtemp(prefix="boxloc-fuzz-"))).resolve()
    wd.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(wd / "failures", ignore_errors=True)
    logs = default_sample_logs() if sample_logs is None else [Path(p) for p in sample_logs]
    t0 = time.perf_counter()
    corpus = build_corpus(wd / "corpus", logs)
    t_corpus = time.perf_counter() - t0
    cases = plan(n, seed)
    results: list[dict[str, Any]] = []

    def on_result(r: dict[str, Any]) -> None:
        results.append(r)
        if progress and len(results) % 500 == 0:
            bad = sum(x["status"] == "failure" for x in results)
            print(f"fuzz: {len(results)}/{n} cases, {bad} failure(s), "
                  f"{time.perf_counter() - t1:.0f} s", file=sys.stderr, flush=True)

    t1 = time.perf_counter()
    pool = _Pool(max(1, int(workers)), corpus, wd, mem_bound_mb, timeout_s)
    if cases:
        pool.run(cases, on_result)
    seconds = time.perf_counter() - t1
    results.sort(key=lambda r: r["case"])
    report = summarize(results, seconds)
    report.update({
        "seed": int(seed), "workers": max(1, int(workers)), "timeout_s": timeout_s,
        "mem_bound_mb": mem_bound_mb, "corpus_seconds": round(t_corpus, 2),
        "sample_logs": [str(p) for p in logs], "worker_restarts": pool.restarts,
        "worker": pool.worker_info,
        "failures_dir": str(wd / "failures") if report["outcomes"]["failure"] else None,
    })
    (wd / "fuzz.json").write_text(json.dumps(report, indent=1, default=str) + "\n")
    if not keep:
        if report["outcomes"]["failure"]:
            shutil.rmtree(wd / "tmp", ignore_errors=True)
        else:
            shutil.rmtree(wd, ignore_errors=True)
            report["failures_dir"] = None
    return report


def summarize(results: Sequence[dict[str, Any]], seconds: float) -> dict[str, Any]:
    """Counts per outcome and category, the failures, the commonest refusals."""
    outcomes = Counter({"ok": 0, "error": 0, "failure": 0})
    by_cat: dict[str, Counter[str]] = {c: Counter({"cases": 0, "ok": 0, "error": 0,
                                                   "failure": 0}) for c in CATEGORIES}
    kinds: Counter[str] = Counter()
    steps: Counter[str] = Counter()
    errors: Counter[str] = Counter()
    mems = [r["mem_mb"] for r in results if r.get("mem_mb") is not None]
    secs = [r["seconds"] for r in results if r.get("seconds") is not None]
    for r in results:
        outcomes[r["status"]] += 1
        c = by_cat.setdefault(r["category"], Counter())
        c["cases"] += 1
        c[r["status"]] += 1
        if r["status"] == "failure":
            kinds[r["what"] or "?"] += 1
        if r["status"] == "error":
            errors[_normalize(r["detail"])] += 1
        for st in r.get("steps", {}).values():
            steps[st] += 1
    fails = [{k: r[k] for k in ("case", "category", "kind", "what", "step", "detail")}
             for r in results if r["status"] == "failure"]
    return {
        "cases": len(results),
        "outcomes": dict(outcomes),
        "reader_calls": sum(steps.values()),
        "reader_call_outcomes": dict(steps),
        "by_category": {k: dict(v) for k, v in by_cat.items()},
        "failure_kinds": dict(kinds),
        "failures": fails[:_MAX_LISTED],
        "top_errors": [{"count": k, "message": m} for m, k in errors.most_common(10)],
        "seconds": round(seconds, 1),
        "cases_per_s": round(len(results) / seconds, 2) if seconds > 0 else None,
        "case_seconds_max": round(max(secs), 2) if secs else None,
        "case_mem_mb_max": round(max(mems), 1) if mems else None,
    }


def _normalize(detail: str) -> str:
    """An error message with paths and numbers blanked, to count kinds of refusal."""
    import re

    s = re.sub(r"/\S+", "PATH", detail)
    s = re.sub(r"\d+", "N", s)
    return s[:120]

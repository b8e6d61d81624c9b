"""The ``fuzz`` section of ``boxloc bench``, and ``python -m recorder.fuzz`` (a run, or one
saved failing case again).
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from boxloc.errors import BoxlocError, InputError
from recorder.fuzz.bags import bag_steps
from recorder.fuzz.cases import Case, Job
from recorder.fuzz.corpus import corpus_at, default_sample_logs
from recorder.fuzz.execute import run_step
from recorder.fuzz.generate import generate, write_cases
from recorder.fuzz.log_bytes import log_steps
from recorder.fuzz.run import run_fuzz
from recorder.fuzz.scan_files import scan_file_steps


def fuzz_section(ctx: Any) -> dict[str, Any]:
    """The ``fuzz`` section of ``boxloc bench``: ``ctx.n`` cases seeded with ``ctx.seed``
    (``boxloc bench --fuzz N`` gives N), failing cases saved under ``OUT/fuzz/``."""
    wd = Path(ctx.out) / "fuzz" if getattr(ctx, "out", None) is not None else None
    report = run_fuzz(int(ctx.n), int(ctx.seed), workdir=wd, progress=True)
    report.pop("sample_logs", None)
    return report


def reproduce(case_dir: str | os.PathLike[str]) -> dict[str, Any]:
    """Run a saved failing case again in this process (tracebacks are printed)."""
    d = Path(case_dir)
    info = json.loads((d / "case.json").read_text())
    case = Case(int(info["case"]), str(info["category"]), int(info["seed"]))
    tmp = Path(tempfile.mkdtemp(prefix="boxloc-fuzz-case-"))
    try:
        if case.category in ("scan", "pipeline"):
            job = generate(case, {}, tmp)
        else:
            for f in d.iterdir():
                if f.is_file() and f.name != "case.json":
                    shutil.copy2(f, tmp / f.name)
            job = _steps_for_saved(case, info, tmp)
        steps: dict[str, dict[str, Any]] = {}
        out = {"case": case.index, "kind": job.kind, "steps": steps}
        for name, fn in job.steps:
            status, what, detail, tb = run_step(fn)
            steps[name] = {"status": status, "what": what, "detail": detail}
            if tb:
                print(tb, file=sys.stderr)
        return out
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _steps_for_saved(case: Case, info: dict[str, Any], d: Path) -> Job:
    """The steps of a file case, on its saved input (the corpus is not needed)."""
    files = sorted(p for p in d.iterdir() if p.name.startswith("fuzzed"))
    if case.category == "bag" and files:
        return Job(info.get("kind", ""), bag_steps(files[0], d))
    mcap = [p for p in files if p.suffix == ".mcap"]
    if mcap:
        return Job(info.get("kind", ""), log_steps(mcap[0], d))
    if not files:
        raise FileNotFoundError(f"no saved input in {d}")
    kw = dict(info.get("read_kw") or {})
    return Job(info.get("kind", ""), scan_file_steps(files[0], kw, d,
                                                     labels=files[0].suffix in (".pcd", ".ply")))


def main(argv: Sequence[str] | None = None) -> int:
    import argparse

    import recorder.fuzz

    # the package's summary line, as ``--help`` showed it when the fuzzer was one module
    summary = (recorder.fuzz.__doc__ or "").split("\n")[0]
    ap = argparse.ArgumentParser(prog="python -m recorder.fuzz", description=summary)
    ap.add_argument("--n", type=int, default=200, help="number of cases")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="work directory (kept)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--case", default=None, help="re-run a saved failing case directory")
    ap.add_argument("--write-cases", default=None, metavar="DIR",
                    help="only write the inputs of the --n cases into DIR/case-NNNNN/ (and "
                         "DIR/cases.json), without running them")
    ap.add_argument("--corpus", default=None, metavar="DIR",
                    help="with --write-cases: the corpus directory, reused if it holds one "
                         "(default DIR/corpus); share it to compare two runs' cases")
    a = ap.parse_args(argv)
    try:
        return _main(a)
    except BoxlocError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


def _main(a: Any) -> int:
    if a.n < 0:
        raise InputError(f"--n must be >= 0, got {a.n}")
    if a.corpus and not a.write_cases:
        raise InputError("--corpus is only used with --write-cases")
    if a.write_cases:
        out = Path(a.write_cases)
        corpus = corpus_at(Path(a.corpus) if a.corpus else out / "corpus",
                           default_sample_logs())
        rows = write_cases(a.n, a.seed, out, corpus)
        by_cat = Counter(r["category"] for r in rows)
        print(json.dumps({"cases": len(rows), "by_category": dict(by_cat),
                          "files": sum(len(r["files"]) for r in rows),
                          "index": str(out / "cases.json")}, indent=1))
        return 0
    if a.case:
        print(json.dumps(reproduce(a.case), indent=1))
        return 0
    rep = run_fuzz(a.n, a.seed, workdir=a.out, workers=a.workers, progress=True)
    print(json.dumps({k: v for k, v in rep.items() if k != "failures"}, indent=1))
    for f in rep["failures"]:
        print(f"FAILURE case {f['case']} {f['category']} {f['kind']} [{f['step']}] "
              f"{f['what']}: {f['detail']}")
    return 1 if rep["outcomes"]["failure"] else 0

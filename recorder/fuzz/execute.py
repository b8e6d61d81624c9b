"""Running one case in this process: each step's outcome (ok, error, failure), time and
peak memory; a failing case's input saved for reproduction.
"""

from __future__ import annotations

import json
import shutil
import sys
import time
import traceback
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from boxloc.errors import BoxlocError
from recorder.fuzz.cases import Case, Job
from recorder.fuzz.generate import generate


def _proc_kb(key: str) -> int | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


def _reset_peak() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _traceback(e: BaseException) -> str:
    return "".join(traceback.format_exception(type(e), e, e.__traceback__))[-4000:]


def run_step(fn: Callable[[], Any]) -> tuple[str, str | None, str, str]:
    """Run one reader call; return ``(status, failure kind, detail, traceback)``."""
    try:
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore")
            fn()
    except BoxlocError as e:
        msg = str(e)
        if not msg.strip() or "\n" in msg or "\r" in msg:
            return ("failure", "message", f"{type(e).__name__} whose message is not one line: "
                    f"{msg[:300]!r}", _traceback(e))
        if "not enough memory" in msg:
            return "failure", "memory", f"{type(e).__name__}: {msg[:300]}", _traceback(e)
        return "error", None, f"{type(e).__name__}: {msg[:300]}", ""
    except MemoryError as e:
        return "failure", "memory", f"MemoryError: {str(e)[:300]}", _traceback(e)
    except KeyboardInterrupt:
        raise
    except BaseException as e:  # noqa: BLE001 - every other exception is a finding
        return "failure", "exception", f"{type(e).__name__}: {str(e)[:300]}", _traceback(e)
    return "ok", None, "", ""


_RANK = {"ok": 0, "error": 1, "failure": 2}


def run_case(case: Case, corpus: dict[str, Any], tmp: Path, *, mem_bound_mb: float,
             failures_dir: Path | None = None) -> dict[str, Any]:
    """Generate and run one case in this process; return its outcome."""
    d = tmp / f"case-{case.index:05d}"
    shutil.rmtree(d, ignore_errors=True)
    measured = _reset_peak()
    rss0 = _proc_kb("VmRSS") or 0
    t0 = time.perf_counter()
    out: dict[str, Any] = {"case": case.index, "category": case.category, "kind": "",
                           "status": "ok", "what": None, "step": "", "detail": "",
                           "traceback": "", "steps": {}}
    try:
        job = generate(case, corpus, d)
    except Exception as e:  # noqa: BLE001 - a harness bug: reported, never hidden
        out.update(status="failure", what="harness", step="generate",
                   detail=f"{type(e).__name__}: {e}"[:300], traceback=_traceback(e))
        job = Job("generate-failed")
    out["kind"] = job.kind
    out["read_kw"] = job.read_kw
    for name, fn in job.steps:
        status, what, detail, tb = run_step(fn)
        out["steps"][name] = status
        if _RANK[status] > _RANK[out["status"]]:
            out.update(status=status, what=what, step=name, detail=detail, traceback=tb)
    out["seconds"] = time.perf_counter() - t0
    hwm = _proc_kb("VmHWM") if measured else None
    out["mem_mb"] = None if hwm is None else max(0.0, (hwm - rss0) / 1024)
    if out["mem_mb"] is not None and out["mem_mb"] > mem_bound_mb and out["status"] != "failure":
        out.update(status="failure", what="memory", step="(whole case)",
                   detail=f"peak resident memory grew by {out['mem_mb']:.0f} MB "
                          f"(bound {mem_bound_mb:.0f} MB)")
    if out["status"] == "failure" and failures_dir is not None:
        save_failure(out, case, d, failures_dir)
    shutil.rmtree(d, ignore_errors=True)
    return out


def save_failure(out: dict[str, Any], case: Case, src: Path | None, failures_dir: Path) -> Path:
    """Keep a failing case's input files and ``case.json`` for reproduction."""
    dst = failures_dir / f"case-{case.index:05d}"
    shutil.rmtree(dst, ignore_errors=True)
    if src is not None and src.is_dir():
        shutil.copytree(src, dst, ignore=shutil.ignore_patterns("recovered.mcap*",
                                                                "roundtrip.mcap*", "run.mcap*"))
    dst.mkdir(parents=True, exist_ok=True)
    info = {**out, "seed": case.seed, "reproduce": f"{sys.executable} -m recorder.fuzz "
                                                   f"--case {dst}"}
    (dst / "case.json").write_text(json.dumps(info, indent=1, default=str) + "\n")
    return dst

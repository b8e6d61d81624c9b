"""Worker processes with a per-case time limit: a worker that overruns is killed and
replaced; one that dies is a crash failure.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import resource
import shutil
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from recorder.fuzz.cases import _RESTART_GROWTH_MB, CATEGORIES, Case
from recorder.fuzz.execute import _proc_kb, _reset_peak, run_case, run_step, save_failure
from recorder.fuzz.generate import generate

#: The seed of the warm-up cases (case ``i`` of it in category ``i``). Their inputs are
#: small and each ends ``ok`` or ``error`` within seconds; a warm-up case that hung or
#: crashed would stop the worker from starting.
_WARM_UP_SEED = 0


def _warm_up(corpus: dict[str, Any], tmp: Path) -> None:
    """Import and JIT-compile everything once, so that per-case memory and time are the
    case's own."""
    import cv2  # noqa: F401
    import open3d  # noqa: F401

    from boxloc.io import read_scan
    from recorder.commands import log_info

    for i, cat in enumerate(CATEGORIES):
        # A non-negative index: numpy refuses negative seed entropy, and the warm-up cases
        # once had negative indexes, so that every one of them failed before it ran.
        case = Case(i, cat, _WARM_UP_SEED)
        with contextlib.suppress(Exception):
            job = generate(case, corpus, tmp / "warm")
            for _, fn in job.steps:
                run_step(fn)
    with contextlib.suppress(Exception):
        read_scan(corpus["npz"][0])
        log_info(corpus["small_logs"][0])
    shutil.rmtree(tmp / "warm", ignore_errors=True)


def _worker_main(conn: Any, corpus: dict[str, Any], workdir: str, slot: int,
                 mem_bound_mb: float) -> None:
    for var in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    wd = Path(workdir)
    tmp = wd / "tmp" / f"worker-{slot}"
    tmp.mkdir(parents=True, exist_ok=True)
    os.chdir(tmp)  # a payload that ran would leave its file here
    # Libraries (Open3D, OpenCV) may print; keep it out of the caller's terminal.
    logf = os.open(str(wd / f"worker-{slot}.log"), os.O_WRONLY | os.O_CREAT | os.O_APPEND)
    os.dup2(logf, 1)
    os.dup2(logf, 2)
    import faulthandler

    faulthandler.enable()  # a native crash leaves the Python stack in the worker's log
    _warm_up(corpus, tmp)
    base_rss = _proc_kb("VmRSS") or 0
    vm = _proc_kb("VmSize")
    limit = None
    if vm is not None:
        # A hard ceiling well above the bound: a runaway allocation fails fast instead of
        # taking the machine's memory.
        limit = int((vm + 4 * mem_bound_mb * 1024 + 1024 * 1024) * 1024)
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_AS, (limit, resource.RLIM_INFINITY))
    conn.send(("ready", {"rss_mb": base_rss / 1024, "as_limit_mb": limit and limit / 2**20,
                         "peak_check": _reset_peak()}))
    failures = wd / "failures"
    while True:
        try:
            msg = conn.recv()
        except EOFError:
            return
        if msg is None:
            return
        case = Case(**msg)
        os.write(2, f"case {case.index} ({case.category})\n".encode())
        out = run_case(case, corpus, tmp, mem_bound_mb=mem_bound_mb, failures_dir=failures)
        rss = _proc_kb("VmRSS") or 0
        out["restart"] = (rss - base_rss) / 1024 > _RESTART_GROWTH_MB
        if (tmp / "PWNED").exists():
            out.update(status="failure", what="executed", step="(whole case)",
                       detail="a payload from the input was executed (PWNED was created)")
        conn.send(out)
        if out["restart"]:
            return


@dataclass
class _Slot:
    index: int
    proc: Any = None
    conn: Any = None
    state: str = "down"  # down, starting, idle, busy
    case: Case | None = None
    t0: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)
    history: deque[int] = field(default_factory=lambda: deque(maxlen=5))


class _Pool:
    """Worker processes with a per-case time limit: a worker that overruns is killed (its
    case is a timeout failure) and replaced; one that dies is a crash failure."""

    def __init__(self, n: int, corpus: dict[str, Any], workdir: Path, mem_bound_mb: float,
                 timeout_s: float, start_timeout_s: float = 600.0) -> None:
        import multiprocessing as mp

        self.ctx = mp.get_context("spawn")
        self.corpus, self.workdir = corpus, workdir
        self.mem_bound_mb, self.timeout_s = mem_bound_mb, timeout_s
        self.start_timeout_s = start_timeout_s
        self.slots = [_Slot(i) for i in range(n)]
        self.restarts = 0
        self.worker_info: dict[str, Any] = {}

    def _start(self, s: _Slot) -> None:
        parent, child = self.ctx.Pipe()
        s.proc = self.ctx.Process(target=_worker_main, daemon=True,
                                  args=(child, self.corpus, str(self.workdir), s.index,
                                        self.mem_bound_mb))
        s.proc.start()
        child.close()
        s.conn, s.state, s.case, s.t0 = parent, "starting", None, time.monotonic()

    def _stop(self, s: _Slot, kill: bool) -> None:
        if s.proc is not None:
            if kill and s.proc.is_alive():
                s.proc.kill()  # our own child, by its handle
            else:
                with contextlib.suppress(OSError, BrokenPipeError):
                    s.conn.send(None)
            s.proc.join(timeout=30)
            if s.proc.is_alive():
                s.proc.kill()
                s.proc.join(timeout=10)
        if s.conn is not None:  # stopping a slot twice (its start failed) is harmless
            with contextlib.suppress(OSError):
                s.conn.close()
        s.proc, s.conn, s.state, s.case = None, None, "down", None

    def run(self, cases: Sequence[Case], on_result: Callable[[dict[str, Any]], None]) -> None:
        from multiprocessing.connection import wait

        todo = deque(cases)
        for s in self.slots:
            self._start(s)
        try:
            while todo or any(s.state == "busy" for s in self.slots):
                for s in self.slots:
                    if s.state == "down":
                        self.restarts += 1
                        self._start(s)
                    if s.state == "idle" and todo:
                        s.case = todo.popleft()
                        s.history.append(s.case.index)
                        s.conn.send(dataclasses.asdict(s.case))
                        s.state, s.t0 = "busy", time.monotonic()
                live = [s.conn for s in self.slots if s.state in ("starting", "busy")]
                for ready in wait(live, timeout=0.5):
                    s = next(x for x in self.slots if x.conn is ready)
                    try:
                        msg = s.conn.recv()
                    except (EOFError, OSError):
                        self._died(s, on_result)
                        continue
                    if s.state == "starting":
                        s.state = "idle"
                        s.info = msg[1]
                        self.worker_info = msg[1]
                        continue
                    s.state, case = "idle", s.case
                    s.case = None
                    on_result(msg)
                    if msg.get("restart"):
                        self._stop(s, kill=False)
                now = time.monotonic()
                for s in self.slots:
                    if s.state == "busy" and now - s.t0 > self.timeout_s:
                        case = s.case
                        self._stop(s, kill=True)
                        assert case is not None
                        on_result(self._lost(case, "timeout",
                                             f"no result within {self.timeout_s:g} s; the "
                                             "worker was killed"))
                    elif s.state == "starting" and now - s.t0 > self.start_timeout_s:
                        raise RuntimeError("a fuzz worker did not start")
        finally:
            for s in self.slots:
                self._stop(s, kill=s.state == "busy")

    def _died(self, s: _Slot, on_result: Callable[[dict[str, Any]], None]) -> None:
        case, state = s.case, s.state
        before = [i for i in s.history if case is None or i != case.index]
        s.history.clear()
        code = s.proc.exitcode if s.proc is not None else None
        self._stop(s, kill=True)
        if state == "starting":
            raise RuntimeError(f"a fuzz worker died while starting (exit code {code}); see "
                               f"{self.workdir}/worker-{s.index}.log")
        if case is not None:
            on_result(self._lost(case, "crash", f"the worker process died (exit code {code}); "
                                 f"its previous cases (a native memory error can surface "
                                 f"later): {before}"))

    def _lost(self, case: Case, what: str, detail: str) -> dict[str, Any]:
        out = {"case": case.index, "category": case.category, "kind": "", "status": "failure",
               "what": what, "step": "", "detail": detail, "traceback": "", "steps": {},
               "seconds": None, "mem_mb": None}
        # The inputs are a function of the case alone: write them again for reproduction.
        d = self.workdir / "tmp" / "lost"
        shutil.rmtree(d, ignore_errors=True)
        try:
            job = generate(case, self.corpus, d)
            out["kind"], out["read_kw"] = job.kind, job.read_kw
        except Exception as e:  # noqa: BLE001
            out["kind"] = f"(cannot regenerate: {e})"
        save_failure(out, case, d, self.workdir / "failures")
        shutil.rmtree(d, ignore_errors=True)
        return out

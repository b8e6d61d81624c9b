"""Run one function over many logs: in this process, on local processes, or on Dask.

Every executor takes ``fn(path) -> ReplayOutcome`` (a picklable callable, typically a
``functools.partial`` of :func:`replay.replay.replay_log`) and the logs, and returns the
outcomes in the order of the logs, whatever order they finished in. A task whose worker
dies is retried; a task that still cannot finish becomes an error outcome naming its log,
so one bad log never loses the others.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.connection import wait as mp_wait
from pathlib import Path
from typing import Any

from boxloc.errors import InputError
from replay.replay import ReplayOutcome

ReplayFn = Callable[[Path], ReplayOutcome]
#: Retries of a log whose worker was lost (a killed process, a lost Dask worker).
RETRIES = 2
#: Modules the local worker processes import once, before forking each worker.
_PRELOAD = ["replay.replay", "boxloc.pipeline", "recorder.mcap.log", "recorder.mcap.sink"]


def default_jobs() -> int:
    """All cores (at least 1)."""
    return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def progress_bar(total: int, description: str, enabled: bool = True) -> Iterator[Any]:
    """A rich progress bar on stderr with count, elapsed time and ETA; yields ``advance()``."""
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                   TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                   console=Console(stderr=True), disable=not enabled, transient=False)
    with bar:
        task = bar.add_task(description, total=total)
        yield lambda n=1: bar.advance(task, n)


def _crashed(path: Path, why: str) -> ReplayOutcome:
    return ReplayOutcome(input=str(path), error=f"{path}: {why}")


def run_serial(paths: Sequence[Path], fn: ReplayFn, *,
               progress: bool = False) -> list[ReplayOutcome]:
    """Run ``fn`` on each log in this process, in order."""
    out = []
    with progress_bar(len(paths), "replay", progress) as advance:
        for p in paths:
            try:
                out.append(fn(p))
            except Exception as e:  # noqa: BLE001 - fn should not raise; if it does, name the log
                out.append(_crashed(p, f"replay failed: {type(e).__name__}: {e}"))
            advance()
    return out


#: Thread pools pinned to one thread in worker processes (one process per core already).
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                "NUMBA_NUM_THREADS")


def _pin_threads() -> None:
    """One thread per BLAS/OpenMP/numba pool in the processes started from here on (unless
    the user chose): ``jobs`` processes with a pool of ``cores`` threads each would fight
    over the cores. The environment is inherited by the forkserver when it starts."""
    for var in _THREAD_VARS:
        os.environ.setdefault(var, "1")


def _context() -> Any:
    # forkserver, not fork: the parent runs a progress thread (and maybe Dask or numba
    # threads), and forking a threaded process can deadlock the child. The server imports
    # the pipeline once, so each worker starts warm.
    ctx: multiprocessing.context.BaseContext
    try:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(_PRELOAD)
    except ValueError:  # no forkserver on this platform
        ctx = multiprocessing.get_context("spawn")
    return ctx


def _worker_main(conn: Connection, fn: ReplayFn) -> None:
    """A local worker process: replay the logs it is sent, one at a time, until ``None``."""
    try:
        with contextlib.suppress(KeyboardInterrupt):  # Ctrl-C: the parent reports it
            _serve(conn, fn)
    finally:
        # A revision's replay subprocesses end with their worker (no atexit in here).
        from replay.versions import close_workers

        close_workers()


def _serve(conn: Connection, fn: ReplayFn) -> None:
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        i, path = msg
        try:
            out = fn(path)
        except Exception as e:  # noqa: BLE001 - fn should not raise; if it does, name the log
            out = _crashed(path, f"replay failed: {type(e).__name__}: {e}")
        conn.send((i, out))


@dataclass
class _Slot:
    """One worker process and the log it is replaying (None: idle)."""

    proc: Any
    conn: Connection
    task: int | None = None


class _Pool:
    """Worker processes that each replay one log at a time.

    Unlike ``ProcessPoolExecutor``, a worker that dies (killed, out of memory, a crash in
    native code) costs only the log it was replaying: that log is retried on a new worker,
    the others are not touched.
    """

    def __init__(self, fn: ReplayFn, jobs: int) -> None:
        self.fn, self.jobs, self.ctx = fn, jobs, _context()
        self.slots: list[_Slot] = []
        self.procs: list[Any] = []

    def start(self) -> _Slot:
        parent, child = self.ctx.Pipe()
        # Not a daemon: a replay may itself start processes (Config.workers > 1).
        proc = self.ctx.Process(target=_worker_main, args=(child, self.fn), daemon=False)
        proc.start()
        child.close()
        slot = _Slot(proc, parent)
        self.slots.append(slot)
        self.procs.append(proc)
        return slot

    def retire(self, slot: _Slot) -> None:
        """Tell a worker to stop (if it still listens) and forget it."""
        self.slots.remove(slot)
        with contextlib.suppress(OSError, ValueError):
            slot.conn.send(None)
        with contextlib.suppress(OSError):
            slot.conn.close()

    def close(self) -> None:
        """Stop every worker: politely, then (after 10 s, or at once on an interrupt) not."""
        for slot in list(self.slots):
            self.retire(slot)
        for p in self.procs:
            p.join(timeout=10)
            if p.is_alive():
                p.terminate()
                p.join(timeout=5)


def run_local(paths: Sequence[Path], fn: ReplayFn, jobs: int | None = None, *,
              progress: bool = False, pool: bool | None = None,
              retries: int = RETRIES) -> list[ReplayOutcome]:
    """Run ``fn`` on every log on ``jobs`` local processes.

    Parameters
    ----------
    paths : sequence of Path
        The logs.
    fn : callable
        ``fn(path) -> ReplayOutcome``, picklable.
    jobs : int, optional
        Worker processes; default all cores.
    progress : bool
        Show a progress bar with ETA on stderr.
    pool : bool, optional
        Use worker processes even for one job (default: only when more than one job and
        more than one log; otherwise the logs are replayed in this process).
    retries : int
        How often a log is given to a new worker after its worker process died.

    Returns
    -------
    list of ReplayOutcome
        In the order of ``paths``.
    """
    paths = [Path(p) for p in paths]
    jobs = default_jobs() if jobs is None else int(jobs)
    if jobs < 1:
        raise InputError(f"--jobs must be >= 1, got {jobs}")
    if not paths:
        return []
    if not (pool if pool is not None else min(jobs, len(paths)) > 1):
        return run_serial(paths, fn, progress=progress)
    _pin_threads()
    results: dict[int, ReplayOutcome] = {}
    tries = dict.fromkeys(range(len(paths)), 0)
    queue = deque(range(len(paths)))
    workers = _Pool(fn, min(jobs, len(paths)))

    def feed(slot: _Slot) -> None:
        while queue:
            slot.task = queue.popleft()
            try:
                slot.conn.send((slot.task, paths[slot.task]))
                return
            except OSError:  # it died between two logs: not the log's fault
                queue.appendleft(slot.task)
                workers.retire(slot)
                slot = workers.start()
        slot.task = None
        workers.retire(slot)

    try:
        with progress_bar(len(paths), f"replay ({jobs} jobs)", progress) as advance:
            for _ in range(workers.jobs):
                feed(workers.start())
            while len(results) < len(paths):
                busy = [s for s in workers.slots if s.task is not None]
                ready = set(mp_wait([s.conn for s in busy] + [s.proc.sentinel for s in busy]))
                for s in busy:
                    if s.conn not in ready and s.proc.sentinel not in ready:
                        continue
                    i = s.task
                    assert i is not None
                    try:
                        got, out = s.conn.recv()
                    except (EOFError, OSError):  # the worker died with the log in hand
                        tries[i] += 1
                        workers.retire(s)
                        s.proc.join(timeout=5)  # for its exit code
                        if tries[i] > retries:
                            results[i] = _crashed(paths[i], f"its worker process died "
                                                  f"{tries[i]} times (exit code "
                                                  f"{s.proc.exitcode})")
                            advance()
                        else:
                            queue.appendleft(i)
                        if queue:
                            feed(workers.start())
                        continue
                    results[got] = out
                    advance()
                    feed(s)
    finally:
        workers.close()
    return [results[i] for i in range(len(paths))]


def run_dask(paths: Sequence[Path], fn: ReplayFn, scheduler_address: str, *,
             progress: bool = False, retries: int = RETRIES, timeout_s: float = 30.0,
             cleanup: Callable[[], Any] | None = None) -> list[ReplayOutcome]:
    """Run ``fn`` on every log on an existing Dask distributed cluster, one task per log.

    Parameters
    ----------
    scheduler_address : str
        ``tcp://HOST:PORT`` of the scheduler.
    retries : int
        Retries of a task that raised. A task whose worker was lost is rescheduled by the
        scheduler (up to its ``allowed-failures``), with the same arguments, so the same
        result.
    timeout_s : float
        Time allowed to connect to the scheduler.
    cleanup : callable, optional
        Run once on every worker at the end (e.g. stop a revision's replay subprocesses:
        the workers outlive the run).

    Returns
    -------
    list of ReplayOutcome
        In the order of ``paths``; the same as :func:`run_local` gives.

    Notes
    -----
    The workers must see the logs and the output directory at the same paths, and have
    this code installed (the same environment).

    Raises
    ------
    InputError
        If the scheduler cannot be reached (before any work).
    """
    from distributed import Client, as_completed

    paths = [Path(p) for p in paths]
    if not paths:
        return []
    try:
        client = Client(scheduler_address, timeout=f"{timeout_s}s", set_as_default=False)
    except (OSError, TimeoutError, ValueError) as e:
        raise InputError(f"cannot connect to the Dask scheduler at {scheduler_address}: "
                         f"{str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
    results: dict[int, ReplayOutcome] = {}
    try:
        # Keys name the log (readable on the dashboard) and are unique per log and run.
        keys = [f"replay-{i}-{p.name}-{os.urandom(4).hex()}" for i, p in enumerate(paths)]
        futs = client.map(fn, paths, key=keys, retries=retries, pure=False)
        index = {f.key: i for i, f in enumerate(futs)}
        with progress_bar(len(paths), "replay (dask)", progress) as advance:
            for f in as_completed(futs, loop=client.loop):
                i = index[f.key]
                try:
                    results[i] = f.result()
                except Exception as e:  # noqa: BLE001 - KilledWorker, a crash after retries
                    results[i] = _crashed(paths[i], f"task failed on the cluster: "
                                          f"{type(e).__name__}: {e}")
                advance()
    finally:
        if cleanup is not None:
            with contextlib.suppress(Exception):  # best effort: a worker may be gone
                client.run(cleanup)
        client.close()
    return [results[i] for i in range(len(paths))]

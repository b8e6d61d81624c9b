"""The benchmarks' worker processes: each scan in a child process, killed at a deadline.

The matrix, packed-layer and bare-plane benches run their scans here. :func:`run_tasks`
keeps ``jobs`` worker processes busy with a list of tasks and hands each result to the
bench as it ends; a worker that passes its deadline is killed (the scan is a ``timeout``),
one that dies is an ``error``, and either way the bench gets a result for every task.

A bench says what a worker does with a task by its *task function* (:data:`TaskFn`),
``fn(conn, task, spec, payload, localizer, cache) -> result``: ``spec`` is the scene,
``payload`` what the bench runs it with (a :class:`~boxloc.config.Config`, or a job
description), ``cache`` a dict the worker keeps across its tasks. The function sends
``("started", task, meta)`` on ``conn`` when the timed part begins (the deadline starts
again there: the simulation and the localizer have the same limit each) and returns the
result, a dict with at least ``status``.

Messages on a worker's pipe: ``(task, spec, payload)`` or ``None`` (stop) in;
``("ready", threads)``, ``("started", task, meta)`` and ``("done", task, result)`` out.
"""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.connection import wait as mp_wait
from typing import Any

from boxloc.config import Config
from boxloc.errors import InputError

#: ``(scan, config) -> Result``-like: what a bench localizes with.
Localizer = Callable[[Any, Config], Any]
#: A bench's work on one task, in a worker: ``(conn, task, spec, payload, localizer, cache)``.
TaskFn = Callable[[Connection | None, int, Any, Any, Localizer, dict[str, Any]],
                  dict[str, Any]]
#: The error of a task whose worker was killed at its deadline (``limit`` in seconds).
TIMEOUT_ERROR = "no result within the scan limit of {limit:g} s"


def check_run_args(jobs: int, scan_timeout: float | None, held_out: str | None = None) -> None:
    """Refuse a bad worker count, time limit or held-out sensor, in the CLI's words.

    Raises
    ------
    InputError
        If ``held_out`` (when given) is not a sensor of the zoo, ``jobs`` is not an integer
        >= 1 or ``scan_timeout`` is not None and not > 0.
    """
    if held_out is not None:
        from boxloc.simulate import SENSORS

        if held_out not in SENSORS:
            raise InputError(f"--held-out must be one of {', '.join(SENSORS)}, "
                             f"got {held_out!r}")
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise InputError(f"--jobs must be an integer >= 1, got {jobs!r}")
    if scan_timeout is not None and not scan_timeout > 0:
        raise InputError(f"--scan-timeout must be > 0 seconds, got {scan_timeout!r}")


def bench_console(console: Any, progress: bool) -> Any:
    """``console``, or with ``progress`` and none given a rich console on stderr."""
    if console is None and progress:
        from rich.console import Console

        return Console(stderr=True)
    return console


def warmup_spec(specs: Sequence[Any]) -> Any:
    """The first scene at 160 x 120: loads numba's cache and lazy imports, untimed."""
    s = specs[0]
    return dataclasses.replace(s, width=160, height=120, f=float(s.f) * 160 / s.width)


def worker_main(conn: Connection, task_fn: TaskFn, localizer: Localizer,
                warm: tuple[Any, Config] | None) -> None:
    """A worker: pin threads, warm up, then run the tasks it is sent until ``None``."""
    with contextlib.suppress(KeyboardInterrupt, BrokenPipeError, EOFError):
        from boxloc.evaluate.scene_bench import _limit_threads

        threads = _limit_threads()
        if warm is not None:
            from boxloc.simulate import simulate

            with contextlib.suppress(Exception):
                localizer(simulate(warm[0]).scan, warm[1])
        conn.send(("ready", threads))
        cache: dict[str, Any] = {}
        while True:
            msg = conn.recv()
            if msg is None:
                return
            task, spec, payload = msg
            conn.send(("done", task, task_fn(conn, task, spec, payload, localizer, cache)))


def _context() -> Any:
    """fork where there is one: the workers inherit the imported pipeline (and, in tests, a
    monkeypatched localizer); the parent runs no numba and no threads of its own when they
    start, apart from the progress bar's, which they never touch."""
    methods = multiprocessing.get_all_start_methods()
    return multiprocessing.get_context("fork" if "fork" in methods else "spawn")


@dataclass
class _Slot:
    proc: Any
    conn: Connection
    ready: bool = False
    task: int | None = None
    started: float | None = None
    deadline: float = float("inf")
    meta: dict[str, Any] | None = None


class _Workers:
    """``jobs`` worker processes (:func:`worker_main`), each running one task at a time
    under a deadline."""

    def __init__(self, task_fn: TaskFn, localizer: Localizer, jobs: int,
                 warm: tuple[Any, Config] | None, limit: float | None) -> None:
        self.ctx = _context()
        self.task_fn, self.localizer, self.warm, self.limit = task_fn, localizer, warm, limit
        self.slots: list[_Slot] = []
        self.threads: dict[str, Any] | None = None
        self.warmup_timeouts = 0
        for _ in range(jobs):
            self.start()

    def start(self, warm: bool = True) -> _Slot:
        parent, child = self.ctx.Pipe()
        w = self.warm if warm else None
        proc = self.ctx.Process(target=worker_main,
                                args=(child, self.task_fn, self.localizer, w), daemon=True)
        proc.start()
        child.close()
        slot = _Slot(proc, parent, deadline=self.deadline())
        self.slots.append(slot)
        return slot

    def deadline(self) -> float:
        return float("inf") if self.limit is None else time.monotonic() + self.limit

    def kill(self, slot: _Slot) -> None:
        """Stop a worker now (our own child, by its handle) and forget it."""
        self.slots.remove(slot)
        with contextlib.suppress(OSError):
            slot.conn.close()
        if slot.proc.is_alive():
            slot.proc.kill()
        slot.proc.join(timeout=10)

    def close(self) -> None:
        for slot in list(self.slots):
            with contextlib.suppress(OSError, ValueError):
                slot.conn.send(None)
        for slot in list(self.slots):
            slot.proc.join(timeout=5)
            self.kill(slot)

    def send(self, slot: _Slot, task: int, spec: Any, payload: Any) -> None:
        """Start ``task``: the scene ``spec`` and what the worker runs it with."""
        slot.task, slot.started, slot.meta = task, None, None
        slot.deadline = self.deadline()  # the simulation has the same limit
        slot.conn.send((task, spec, payload))

    def wait(self) -> list[_Slot]:
        """The slots with a message, a dead process or a passed deadline."""
        soonest = min((s.deadline for s in self.slots), default=float("inf"))
        timeout = None if soonest == float("inf") else max(0.0, soonest - time.monotonic())
        handles = [s.conn for s in self.slots] + [s.proc.sentinel for s in self.slots]
        hit = set(mp_wait(handles, timeout))
        now = time.monotonic()
        return [s for s in self.slots
                if s.conn in hit or s.proc.sentinel in hit or s.deadline <= now]


def run_tasks(tasks: Sequence[tuple[int, Any, Any]], task_fn: TaskFn, localizer: Localizer,
              jobs: int, limit: float | None, warm: tuple[Any, Config] | None,
              on_done: Callable[[int, dict[str, Any]], None],
              on_start: Callable[[int], None] | None = None, *, fresh: bool = False,
              timeout_error: str = TIMEOUT_ERROR) -> dict[str, Any]:
    """Run every task on worker processes; ``on_done(task, result)`` as each ends.

    Parameters
    ----------
    tasks : sequence of (index, spec, payload)
        Task ``t`` runs ``task_fn(conn, t, spec, payload, localizer, cache)`` in a worker.
    task_fn : TaskFn
        The bench's work on one task (see the module docstring).
    localizer : callable
        Passed to ``task_fn``; with ``warm``, run once per worker before its first task.
    jobs : int
        Worker processes at once (no more than there are tasks).
    limit : float or None
        Seconds a task may take from its start, and again from its ``started`` message;
        None: no limit.
    warm : (spec, Config) or None
        The warm-up scene and configuration, untimed; a worker lost while warming up is
        replaced by a cold one and counted in ``warmup_timeouts``.
    on_done, on_start : callable
        Called with the task's position in ``tasks`` when it ends (with its result) and
        when it is sent to a worker.
    fresh : bool
        A new worker process for every task (the one that ran a task is killed once it has
        answered), so that no task sees another's state.
    timeout_error : str
        The ``error`` of a timed-out task, formatted with ``limit``.

    Returns
    -------
    dict
        ``threads`` (a worker's thread pinning) and ``warmup_timeouts``.

    Notes
    -----
    A result is ``task_fn``'s, or ``{"status": "timeout" | "error", "phase", "error",
    "meta", "wall_ms"}`` made here when the worker was killed at its deadline or died
    (``phase``: ``localize`` after its ``started`` message, else ``simulate``; ``meta``
    that message's; ``wall_ms`` the limit for a timeout).
    """
    queue = list(range(len(tasks)))[::-1]
    pool = _Workers(task_fn, localizer, min(jobs, len(tasks)), warm, limit)
    done = 0
    try:
        while done < len(tasks):
            for s in pool.slots:
                if s.ready and s.task is None and queue:
                    i = queue.pop()
                    pool.send(s, i, tasks[i][1], tasks[i][2])
                    if on_start is not None:
                        on_start(i)
            for s in pool.wait():
                try:
                    msg = s.conn.recv() if s.conn.poll() else None
                except (EOFError, OSError):
                    msg = None
                if msg is not None:
                    if msg[0] == "ready":
                        s.ready, s.deadline = True, float("inf")
                        pool.threads = pool.threads or msg[1]
                    elif msg[0] == "started":
                        s.started, s.meta, s.deadline = time.monotonic(), msg[2], pool.deadline()
                    else:
                        assert s.task is not None
                        on_done(s.task, msg[2])
                        done += 1
                        s.task, s.deadline = None, float("inf")
                        if fresh:
                            pool.kill(s)
                            if queue:
                                pool.start()
                    continue
                alive = s.proc.is_alive()
                if alive and s.deadline > time.monotonic():
                    continue  # woken by its sentinel's neighbour: nothing for this one
                pool.kill(s)
                if s.task is None:  # lost while warming up (or idle): a new one, cold
                    pool.warmup_timeouts += alive
                    pool.start(warm=False)
                    continue
                phase = "localize" if s.started is not None else "simulate"
                if alive:
                    res = {"status": "timeout", "phase": phase, "meta": s.meta,
                           "error": timeout_error.format(limit=limit),
                           "wall_ms": None if limit is None else limit * 1e3}
                else:
                    res = {"status": "error", "phase": phase, "meta": s.meta,
                           "error": f"the worker process died (exit code {s.proc.exitcode})"}
                on_done(s.task, res)
                done += 1
                if queue:
                    pool.start()
    finally:
        pool.close()
    return {"threads": pool.threads, "warmup_timeouts": pool.warmup_timeouts}


def run_with_progress(tasks: Sequence[tuple[int, Any, Any]], task_fn: TaskFn,
                      localizer: Localizer, jobs: int, limit: float | None,
                      warm: tuple[Any, Config] | None,
                      on_done: Callable[[int, dict[str, Any]], None], *, console: Any,
                      label: str, describe: Callable[[int], str],
                      summary: Callable[[int], str]) -> tuple[dict[str, Any], float]:
    """:func:`run_tasks` under a progress bar on ``console`` (None: no bar).

    ``describe(t)`` is the bar's text while task ``t`` runs; ``summary(t)`` the line a
    console that is not a terminal (a log file, which sees no bar) gets when it has ended,
    after ``on_done`` recorded it. Returns :func:`run_tasks`'s dict and the run's seconds.
    """
    from boxloc.evaluate.scene_bench import progress_bar

    t0 = time.monotonic()
    bar, task_id = (None, None)
    if console is not None:
        # the bar's refresh thread lives in the parent; the forked workers never touch it
        bar, task_id = progress_bar(console, label, len(tasks))
    n_done = 0

    def done(t: int, res: dict[str, Any]) -> None:
        nonlocal n_done
        on_done(t, res)
        n_done += 1
        if bar is not None:
            bar.advance(task_id)
            if not console.is_terminal:
                console.print(f"[{n_done}/{len(tasks)}] {summary(t)}", markup=False,
                              highlight=False)

    def start(t: int) -> None:
        if bar is not None:
            bar.update(task_id, description=describe(t))

    try:
        info = run_tasks(tasks, task_fn, localizer, jobs, limit, warm, done, start)
    finally:
        if bar is not None:
            bar.stop()
    return info, time.monotonic() - t0

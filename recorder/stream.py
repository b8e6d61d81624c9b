"""Run the pipeline on a stream of scans in worker processes, results in scan order.

``boxloc run SOURCE... --workers N`` uses :func:`ordered_runs`. Each worker process runs
:func:`boxloc.pipeline.find_graspable_surfaces` with a :class:`Collector`, an observer that
keeps every call it receives (the products are frozen dataclasses of NumPy arrays, so they
pickle), and sends them back as a :class:`ScanRun`. The parent replays them onto the real
observers (Rerun, ROS 2) with :meth:`ScanRun.replay`, one scan after the other in scan
order, as if the pipeline had run in the parent. The log is therefore the same, bit for bit,
as a serial run's: the trial seeds come from the scan and the config, never from the
process, and the observers see the same calls in the same order.

The MCAP messages are encoded in the worker too (with an :class:`Encoding`): a
:class:`recorder.mcap.sink.ScanEncoder`, the code the recorder itself encodes with, turns
the calls into the scan's messages, and the parent only writes them
(:meth:`recorder.mcap.sink.McapRecorder.write_encoded`: compression, the file, fsync). A
simulated scan (:class:`SimScan`) is made in the worker as well: its spec and seed travel,
not the scan. The parent's share of the work per scan is then reading the source and
writing the chunk.

Bounds and failures:

* At most ``window`` (default ``2 N``) items are held between reading and replaying: one
  slow scan never lets the others pile up in memory.
* A scan whose pipeline raises comes back as a :class:`ScanRun` with that error, after the
  products made before it. :meth:`ScanRun.replay` raises it again, so the caller records
  it exactly as a serial run does.
* A scan whose worker dies (killed, out of memory, a crash in native code) is given to a
  new worker once; after a second loss it becomes a :class:`WorkerLost` error of that scan.
  The other scans are not touched.
* Workers ignore SIGINT and SIGTERM: the parent alone decides. When ``stop()`` turns true,
  no new scan is read, and the scans already read are finished and yielded, so the caller
  records everything it started. Closing the generator early (an exception in the caller)
  kills the workers at once.

The workers are forked from a forkserver that has imported the pipeline (as
:mod:`replay.executors` does), never from the parent, which may run threads (the progress
bar, Rerun). This module imports nothing heavy at import time: the parent needs only the
recorder, and the workers only the pipeline.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
import multiprocessing
import os
import signal
import time
from collections import deque
from collections.abc import Callable, Generator, Iterable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.connection import wait as mp_wait
from typing import TYPE_CHECKING, Any

from boxloc.observer import NullObserver

if TYPE_CHECKING:
    from boxloc.config import Config
    from boxloc.observer import Observer
    from boxloc.products import Result
    from boxloc.scan import Scan
    from recorder.mcap.sink import EncodedScan

__all__ = ["Collector", "Encoding", "Job", "RemoteError", "ScanRun", "SimScan", "WorkerLost",
           "default_workers", "ordered_runs", "run_job", "start_early"]

#: New workers a scan gets after the one running it died: one, for a loss that was not the
#: scan's fault (the OOM killer chose it); a scan that kills its worker twice is failed.
RETRIES = 1
#: Modules the forkserver imports once, so that every worker forked from it starts warm
#: (``recorder._stream_warm`` loads the numba kernels by running a small scan).
_PRELOAD = ["recorder.stream", "boxloc.pipeline", "recorder.mcap.sink", "boxloc.simulate",
            "recorder._stream_warm"]
#: Thread pools pinned to one thread in the workers (one process per core already).
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                "NUMBA_NUM_THREADS")
#: Seconds a worker gets to leave after the last scan, before it is killed.
_JOIN_S = 10.0


def default_workers() -> int:
    """The CPUs this process may run on (at least 1): ``--workers 0``."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


# --- one scan, in a worker ------------------------------------------------------------------


@dataclass(frozen=True)
class SimScan:
    """A simulated scan, made where it runs: the spec and the seed travel, not the scan.

    ``make()`` is :func:`boxloc.simulate.simulate` (deterministic: the same arrays, bit for
    bit, in any process) with the scan numbered ``index``.
    """

    spec: Any
    seed: int
    index: int

    def make(self) -> Scan:
        from boxloc.simulate import simulate

        return dataclasses.replace(simulate(self.spec, seed=self.seed).scan, index=self.index)


@dataclass(frozen=True)
class Job:
    """One scan to run (or a simulated one to make first), with the config to run it with."""

    scan: Scan | SimScan
    config: Config

    def make_scan(self) -> Scan:
        """The scan itself (simulated now for a :class:`SimScan`)."""
        return self.scan.make() if isinstance(self.scan, SimScan) else self.scan


@dataclass(frozen=True)
class Encoding:
    """The workers encode each scan's MCAP messages, as the parent's recorder would.

    The arguments of :class:`recorder.mcap.sink.ScanEncoder` that change its bytes: the
    recorder's ``max_points`` and ``config`` (the config of a scan that fails before its
    ``on_scan``).
    """

    max_points: int
    config: Config | None = None


class RemoteError(Exception):
    """An error raised in a worker that does not survive pickling, by its type's name."""


class WorkerLost(RuntimeError):
    """The worker process running a scan died (twice): the scan's error."""


@dataclass(frozen=True)
class _ErrorInfo:
    """A worker's exception as its type's name and message (what the recorder keeps)."""

    type_name: str
    message: str

    def exception(self) -> Exception:
        cls = type(self.type_name, (RemoteError,), {"__module__": __name__})
        return cls(self.message)


def _portable(e: Exception) -> Exception | _ErrorInfo:
    """``e`` itself when it crosses the pipe as the same type with the same message (every
    BoxlocError, ValueError, ...), else its name and message.

    The check rebuilds ``e`` the way unpickling would (from ``__reduce__``) instead of
    unpickling anything.
    """
    from multiprocessing.reduction import ForkingPickler

    try:
        ForkingPickler.dumps(e)
        rv = e.__reduce__()
        back = rv[0](*rv[1])  # type: ignore[operator]
        if type(back) is type(e) and str(back) == str(e):
            return e
    except Exception:  # noqa: BLE001 - any failure to round-trip: keep the name and text
        pass
    return _ErrorInfo(type(e).__name__, str(e))


class Collector(NullObserver):
    """An observer that keeps every call, to be replayed onto other observers later.

    Parameters
    ----------
    scan : Scan
        The scan the pipeline runs on. Calls about it are kept without it (the parent
        replays them with its own copy); a call about another scan keeps that scan.
    """

    def __init__(self, scan: Scan) -> None:
        self.scan = scan
        self.calls: list[tuple[str, Scan | None, tuple[Any, ...]]] = []

    def _keep(self, name: str, scan: Scan, *args: Any) -> None:
        self.calls.append((name, None if scan is self.scan else scan, args))

    def on_scan(self, scan: Scan, config: Any) -> None:
        self._keep("on_scan", scan, config)

    def on_noise(self, scan: Scan, noise: Any) -> None:
        self._keep("on_noise", scan, noise)

    def on_edges(self, scan: Scan, edges: Any) -> None:
        self._keep("on_edges", scan, edges)

    def on_lines(self, scan: Scan, lines: Any) -> None:
        self._keep("on_lines", scan, lines)

    def on_vertices(self, scan: Scan, vertices: Any) -> None:
        self._keep("on_vertices", scan, vertices)

    def on_hypotheses(self, scan: Scan, hypotheses: Any) -> None:
        self._keep("on_hypotheses", scan, hypotheses)

    def on_verification(self, scan: Scan, verification: Any) -> None:
        self._keep("on_verification", scan, verification)

    def on_selection(self, scan: Scan, selection: Any) -> None:
        self._keep("on_selection", scan, selection)

    def on_surfaces(self, scan: Scan, surfaces: Any) -> None:
        self._keep("on_surfaces", scan, surfaces)

    def on_result(self, scan: Scan, result: Any) -> None:
        self._keep("on_result", scan, result)


@dataclass(frozen=True)
class ScanRun:
    """What the pipeline did with one scan: the observer calls it made, then its result or
    its error.

    Attributes
    ----------
    calls : tuple of (str, Scan or None, tuple)
        Observer method, the scan (None: the job's scan) and the other arguments, in order.
    result : Result or None
        None when the pipeline raised.
    error : Exception or None
        What the pipeline raised (possibly as a :class:`RemoteError` subclass of the same
        name and message).
    seconds : float
        Wall time of the pipeline in the worker, s (informational).
    warning : str or None
        The noise model's warning about the scan
        (:func:`boxloc.stages.scan_noise.fit_warning`), made in the worker so that the
        parent never imports the stages.
    encoded : tuple of EncodedScan
        The scan's MCAP messages, encoded in the worker (with an :class:`Encoding`; else
        empty), ending with its result or error: what the parent's recorder writes.
    scan : Scan or None
        The scan the worker made from a :class:`SimScan` (without its cached points).
    unread : str or None
        Why the worker could not make the scan of a :class:`SimScan` (the message of the
        :class:`~boxloc.errors.BoxlocError` it raised); nothing else is set then.
    """

    calls: tuple[tuple[str, Scan | None, tuple[Any, ...]], ...]
    result: Result | None
    error: Exception | _ErrorInfo | None = None
    seconds: float = 0.0
    warning: str | None = None
    encoded: tuple[EncodedScan, ...] = ()
    scan: Scan | None = None
    unread: str | None = None

    def replay(self, scan: Scan, observer: Observer,
               write: Callable[[EncodedScan], None] | None = None) -> Result:
        """Make ``observer`` receive the calls the pipeline made, then return its result or
        raise its error, as :func:`~boxloc.pipeline.find_graspable_surfaces` with that
        observer would have.

        Parameters
        ----------
        scan : Scan
            The parent's copy of the job's scan (what the observers record).
        observer : Observer
            Receives the calls (not the recorder, when ``write`` takes the encoded scan).
        write : callable, optional
            ``write(encoded)`` for each of :attr:`encoded` first
            (:meth:`recorder.mcap.sink.McapRecorder.write_encoded`).
        """
        if write is not None:
            for enc in self.encoded:
                write(enc)
        for name, own, args in self.calls:
            getattr(observer, name)(scan if own is None else own, *args)
        if self.error is not None:
            if isinstance(self.error, _ErrorInfo):
                raise self.error.exception()
            raise self.error
        assert self.result is not None
        return self.result


def run_job(job: Job, encoding: Encoding | None = None) -> ScanRun:
    """Run the pipeline on one scan with a :class:`Collector` (in a worker).

    A failure of the pipeline is the scan's result, as in a serial run: it comes back in
    :attr:`ScanRun.error`, after the calls made before it.

    Parameters
    ----------
    job : Job
        A :class:`SimScan` is simulated here first.
    encoding : Encoding, optional
        Also encode the scan's MCAP messages (:attr:`ScanRun.encoded`) with a
        :class:`recorder.mcap.sink.ScanEncoder`, the recorder's own code; a failed scan
        ends with its error, as the parent's loop ends it in a serial run
        (``McapRecorder.on_error``).
    """
    from boxloc.errors import BoxlocError
    from boxloc.pipeline import find_graspable_surfaces
    from boxloc.stages.scan_noise import fit_warning

    made: Scan | None = None
    if isinstance(job.scan, SimScan):
        try:
            made = job.scan.make()
        except BoxlocError as e:  # a serial run reports it as an unreadable input
            return ScanRun((), None, unread=str(e))
    scan = made if made is not None else job.scan
    assert not isinstance(scan, SimScan)
    col = Collector(scan)
    observer: Observer = col
    encoded: list[EncodedScan] = []
    enc = None
    if encoding is not None:
        from boxloc.observer import FanOut
        from recorder.mcap.sink import ScanEncoder

        enc = ScanEncoder(encoded.append, max_points=encoding.max_points,
                          config=encoding.config)
        observer = FanOut(col, enc)
    t0 = time.perf_counter()
    try:
        result = find_graspable_surfaces(scan, job.config, observer=observer)
    except Exception as e:  # noqa: BLE001 - the scan's failure is its result
        if enc is not None:
            enc.on_error(scan, e)
        return ScanRun(tuple(col.calls), None, _portable(e), time.perf_counter() - t0,
                       encoded=_sendable(encoded), scan=None if made is None else _lean(made))
    seconds = time.perf_counter() - t0
    warning = fit_warning(result.noise) if result.noise is not None else None
    return ScanRun(tuple(col.calls), result, None, seconds, warning, _sendable(encoded),
                   None if made is None else _lean(made))


def _sendable(encoded: list[EncodedScan]) -> tuple[EncodedScan, ...]:
    """The encoded scans with their sensors' caches dropped (a ray table's search tree,
    built by the pipeline): the parent encodes a sensor from its table alone."""
    return tuple(e if _uncached(e.sensor) is e.sensor else
                 dataclasses.replace(e, sensor=_uncached(e.sensor)) for e in encoded)


def _lost(job: Job, exitcode: int | None, times: int) -> ScanRun:
    """The run of a scan whose worker died ``times`` times: recorded with its config."""
    why = f"exit code {exitcode}" if exitcode is None or exitcode >= 0 else \
        f"killed by signal {-exitcode}"
    return ScanRun((("on_scan", None, (job.config,)),), None,
                   WorkerLost(f"the worker process running this scan died {times} time(s) "
                              f"({why})"))


def _failed(job: Job, e: Exception) -> ScanRun:
    """The run of a scan whose result could not be received (decoded) from its worker."""
    return ScanRun((("on_scan", None, (job.config,)),), None,
                   _ErrorInfo(type(e).__name__, f"the worker's result was unreadable: {e}"))


def _uncached(obj: Any) -> Any:
    """A shallow copy of ``obj`` without the values of its ``cached_property`` attributes
    (or ``obj`` itself when it has none)."""
    cached = [k for k, v in vars(type(obj)).items()
              if isinstance(v, functools.cached_property) and k in vars(obj)]
    if not cached:
        return obj
    out = copy.copy(obj)
    for k in cached:
        vars(out).pop(k, None)
    return out


def _lean(scan: Scan) -> Scan:
    """The scan without its cached derived data (``points``: 3x the range's bytes; a ray
    table's search tree), which the worker recomputes the same: less through the pipe."""
    out = _uncached(scan)
    sensor = _uncached(scan.sensor)
    if sensor is not scan.sensor:
        out = copy.copy(out) if out is scan else out
        vars(out)["sensor"] = sensor
    return out


def _worker_main(conn: Connection) -> None:
    """A worker process: run the scans it is sent, one at a time, until ``None``."""
    # The parent alone reacts to Ctrl-C (sent to the whole process group) and SIGTERM: it
    # stops reading scans, and lets the workers finish the ones they have.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):  # the parent is gone
            return
        if msg is None:
            return
        i, job, encoding = msg
        run = run_job(job, encoding)
        try:
            conn.send((i, run))
        except (OSError, EOFError):
            return
        except Exception as e:  # noqa: BLE001 - a product that does not pickle: say so
            conn.send((i, ScanRun(run.calls[:1], None, _ErrorInfo(
                type(e).__name__, f"the scan's products could not be sent: {e}"))))


# --- the pool -------------------------------------------------------------------------------


def _pin_threads() -> None:
    """One thread per BLAS/OpenMP/numba pool in the processes started from here on (unless
    the user chose): N workers with a pool of one thread per core each would fight over the
    cores. The environment is inherited by the forkserver when it starts."""
    for var in _THREAD_VARS:
        os.environ.setdefault(var, "1")


def start_early() -> None:
    """Start the forkserver now: it imports the pipeline (about a second) while the caller
    imports the recorder and opens its sources, instead of after.

    The server is shared by every pool of this process; starting it twice is a no-op.
    """
    _pin_threads()
    if _context().get_start_method() == "forkserver":
        from multiprocessing import forkserver

        forkserver.ensure_running()


def _context() -> Any:
    # forkserver, not fork: the parent runs threads (the progress bar, Rerun), and forking
    # a threaded process can deadlock the child. The server imports the pipeline once, so
    # each worker (and a replacement for one that died) starts warm.
    ctx: Any
    try:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(_PRELOAD)
    except ValueError:  # no forkserver on this platform
        ctx = multiprocessing.get_context("spawn")
    return ctx


@dataclass
class _Worker:
    proc: Any
    conn: Connection
    task: int | None = None


@dataclass
class _Pool:
    """Up to ``size`` worker processes, started when there is a scan for them."""

    size: int
    ctx: Any = field(default_factory=_context)
    live: list[_Worker] = field(default_factory=list)
    procs: list[Any] = field(default_factory=list)

    def has_room(self) -> bool:
        """Whether a scan sent now would start at once (an idle worker, or room for one)."""
        return len(self.live) < self.size or any(w.task is None for w in self.live)

    def free(self) -> _Worker:
        """An idle worker, else a new one (call only when :meth:`has_room`)."""
        for w in self.live:
            if w.task is None:
                return w
        assert len(self.live) < self.size
        _pin_threads()
        parent, child = self.ctx.Pipe()
        # Not a daemon: a worker may start processes itself (Config.workers > 1).
        proc = self.ctx.Process(target=_worker_main, args=(child,), daemon=False,
                                name="boxloc-run-worker")
        proc.start()
        child.close()
        w = _Worker(proc, parent)
        self.live.append(w)
        self.procs.append(proc)
        return w

    def busy(self) -> list[_Worker]:
        return [w for w in self.live if w.task is not None]

    def retire(self, w: _Worker) -> None:
        """Tell a worker to leave (if it still listens) and forget it."""
        self.live.remove(w)
        with contextlib.suppress(OSError, ValueError):
            w.conn.send(None)
        with contextlib.suppress(OSError):
            w.conn.close()

    def close(self, *, at_once: bool) -> None:
        """Stop every worker: politely (``_JOIN_S`` to leave), or at once."""
        for w in list(self.live):
            self.retire(w)
        for p in self.procs:
            if not at_once:
                p.join(timeout=_JOIN_S)
            if p.is_alive():
                p.kill()  # they ignore SIGTERM
                p.join(timeout=5)


def ordered_runs(items: Iterable[Any], workers: int, *,
                 stop: Callable[[], bool] | None = None, window: int | None = None,
                 retries: int = RETRIES, encoding: Encoding | None = None,
                 ) -> Generator[tuple[Any, ScanRun | None], None, None]:
    """Run every :class:`Job` of ``items`` on ``workers`` processes; yield in item order.

    Parameters
    ----------
    items : iterable
        Jobs, read lazily. Any other item (e.g. a read error of a source) is passed through
        in its place, with None for its run.
    workers : int
        Worker processes (>= 1), started as scans arrive.
    stop : callable, optional
        Polled before each item is read: once true, nothing more is read, and the items
        already read are finished and yielded.
    window : int, optional
        Items held at most between being read and being yielded (default ``2 * workers``,
        at least ``workers``).
    retries : int
        New workers a scan gets after its worker died.
    encoding : Encoding, optional
        The workers also encode each scan's MCAP messages (:attr:`ScanRun.encoded`), so
        that the parent only writes them.

    Yields
    ------
    item, ScanRun or None
        Each item with its run, in the order of ``items``.

    Notes
    -----
    Closing the generator before its end (the caller raised) kills the workers at once.
    """
    n = int(workers)
    if n < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    hold = max(n, 2 * n if window is None else int(window))
    stopping = stop or (lambda: False)
    source = iter(items)
    held: dict[int, Any] = {}  # read, not yet yielded
    done: dict[int, ScanRun | None] = {}
    retry: deque[int] = deque()
    tries: dict[int, int] = {}
    n_read = n_out = 0
    exhausted = False

    def next_task() -> int | None:
        nonlocal n_read, exhausted
        if retry:
            return retry.popleft()
        while not exhausted and n_read - n_out < hold and not stopping():
            try:
                item = next(source)
            except StopIteration:
                exhausted = True
                break
            i, n_read = n_read, n_read + 1
            held[i] = item
            if isinstance(item, Job):
                return i
            done[i] = None
        return None

    def lost(w: _Worker, i: int) -> None:
        """Worker ``w`` died with scan ``i``: give it to a new one, or fail it."""
        tries[i] = tries.get(i, 0) + 1
        pool.retire(w)
        w.proc.join(timeout=5)  # for its exit code
        if w.proc.is_alive():  # its pipe broke, it did not: it cannot be reached any more
            w.proc.kill()
            w.proc.join(timeout=5)
        if tries[i] > retries:
            done[i] = _lost(held[i], w.proc.exitcode, tries[i])
        else:
            retry.appendleft(i)

    pool = _Pool(n)
    finished = False
    try:
        while True:
            # 1. every idle worker (or room for a new one) gets the next scan
            while pool.has_room():
                i = next_task()
                if i is None:
                    break
                w, job = pool.free(), held[i]
                w.task = i
                try:
                    lean = job.scan if isinstance(job.scan, SimScan) else _lean(job.scan)
                    w.conn.send((i, Job(lean, job.config), encoding))
                except OSError:  # it died between two scans
                    lost(w, i)
            # 2. the next item in order, as soon as it is there
            if n_out in done:
                item, run = held.pop(n_out), done.pop(n_out)
                n_out += 1
                yield item, run
                continue
            busy = pool.busy()
            if not busy:
                if retry:
                    continue
                break  # nothing running, nothing to read: everything read was yielded
            # 3. wait for a result (or a death)
            ready = set(mp_wait([w.conn for w in busy] + [w.proc.sentinel for w in busy]))
            for w in busy:
                if w.conn not in ready and w.proc.sentinel not in ready:
                    continue
                i = w.task
                assert i is not None
                try:
                    got, run = w.conn.recv()
                except (EOFError, OSError):
                    lost(w, i)
                    continue
                except Exception as e:  # noqa: BLE001 - a result that does not unpickle
                    got, run = i, _failed(held[i], e)
                w.task = None
                done[got] = run
        finished = True
    finally:
        pool.close(at_once=not finished)

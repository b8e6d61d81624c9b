"""Pick outcomes after the fact: an append-only sidecar next to a log.

A log is never rewritten to add an outcome (``boxloc annotate`` must not endanger recorded
data). Outcomes reported after recording go into ``LOG.mcap.outcomes.jsonl``, one JSON
object per line, appended with ``O_APPEND`` under an exclusive lock and fsync'd. Every
reader (:func:`recorder.mcap.log.open_log`) merges the sidecar with the log's own
``/pick/outcome`` channel.

Sidecar line (version 1)::

    {"v": 1, "scan": 3, "surface": 0, "ok": false, "reason": "slipped",
     "source": "annotate", "wall_time_ns": 1718000000000000000}
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

from boxloc.errors import InputError, LogError
from recorder.mcap.encode import PickOutcome

SIDECAR_SUFFIX = ".outcomes.jsonl"
SIDECAR_VERSION = 1
MAX_REASON = 2000
#: A sidecar larger than this is refused (it is hand-sized data, never megabytes).
MAX_SIDECAR_BYTES = 64 << 20


def sidecar_path(log_path: str | os.PathLike[str]) -> Path:
    """``LOG.mcap`` -> ``LOG.mcap.outcomes.jsonl``."""
    return Path(str(log_path) + SIDECAR_SUFFIX)


def _check_outcome_args(scan_index: int, surface_id: int, reason: str) -> None:
    if int(scan_index) < 0:
        raise InputError(f"scan index must be >= 0, got {scan_index}")
    if int(surface_id) < 0:
        raise InputError(f"surface id must be >= 0, got {surface_id}")
    if len(reason) > MAX_REASON:
        raise InputError(f"reason is {len(reason)} characters long; at most {MAX_REASON}")


def append_outcome(
    log_path: str | os.PathLike[str],
    scan_index: int,
    surface_id: int,
    ok: bool,
    reason: str = "",
    *,
    source: str = "annotate",
    check: bool = True,
) -> PickOutcome:
    """Record a pick outcome for a log, in its sidecar. The log itself is only read.

    Parameters
    ----------
    log_path : path
        The ``.mcap`` log.
    scan_index, surface_id : int
        Which surface (``surface_id`` is its row in the scan's surfaces, 0 = first picked).
    ok : bool
        Whether the pick succeeded.
    reason : str
        Free text (why it failed, ...).
    source : str
        Who reports it (``annotate``, ``robot``, ...).
    check : bool
        Check that the log has that scan and surface.

    Raises
    ------
    InputError
        Missing log, or no such scan or surface in it.
    """
    log_path = Path(log_path)
    reason = str(reason)
    _check_outcome_args(scan_index, surface_id, reason)
    if not log_path.is_file():
        raise InputError(f"log not found: {log_path}")
    if check:
        _check_target(log_path, int(scan_index), int(surface_id))
    outcome = PickOutcome(scan_index=int(scan_index), surface_id=int(surface_id), ok=bool(ok),
                          reason=reason, source=str(source), wall_time_ns=time.time_ns(),
                          origin="sidecar")
    line = json.dumps({"v": SIDECAR_VERSION, "scan": outcome.scan_index,
                       "surface": outcome.surface_id, "ok": outcome.ok, "reason": reason,
                       "source": outcome.source, "wall_time_ns": outcome.wall_time_ns},
                      sort_keys=True, ensure_ascii=True) + "\n"
    _append_line(sidecar_path(log_path), line.encode())
    return outcome


def _check_target(log_path: Path, scan_index: int, surface_id: int) -> None:
    from recorder.mcap.log import open_log

    log = open_log(log_path, allow_truncated=True)
    n = None
    for s in log.index():
        if s.index == scan_index:
            n = s.n_surfaces
    if n is None:
        raise InputError(f"{log_path} has no scan {scan_index}")
    if not 0 <= surface_id < n:
        raise InputError(f"scan {scan_index} of {log_path} has {n} surface(s); "
                         f"no surface {surface_id}")


def _append_line(path: Path, data: bytes) -> None:
    """Append one line atomically (O_APPEND, one write, exclusive lock) and fsync it."""
    created = not path.exists()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        try:
            import fcntl

            fcntl.flock(fd, fcntl.LOCK_EX)
        except (ImportError, OSError):  # no flock (Windows, some network FS): O_APPEND only
            pass
        view = memoryview(data)
        while view:
            n = os.write(fd, view)
            view = view[n:]
        os.fsync(fd)
    finally:
        os.close(fd)
    if created:
        try:
            dfd = os.open(path.parent, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except OSError:
            pass


def read_sidecar(log_path: str | os.PathLike[str]) -> list[PickOutcome]:
    """The outcomes in a log's sidecar, in the order they were appended (none if absent).

    A last line without its newline (a writer killed mid-line) is ignored.

    Raises
    ------
    LogError
        A malformed line, or a sidecar of an unknown version.
    """
    p = sidecar_path(log_path)
    if not p.is_file():
        return []
    size = p.stat().st_size
    if size > MAX_SIDECAR_BYTES:
        raise LogError(f"{p} is {size} bytes; larger than the {MAX_SIDECAR_BYTES} allowed")
    text = p.read_bytes()
    lines = text.split(b"\n")
    if lines and lines[-1] != b"":
        lines = lines[:-1]  # torn last line
    out = []
    for no, raw in enumerate(lines, 1):
        if not raw.strip():
            continue
        try:
            d = json.loads(raw)
            out.append(_outcome_from_json(d))
        except (ValueError, TypeError, KeyError, RecursionError) as e:
            raise LogError(f"{p}:{no}: bad outcome line: {str(e)[:200]}") from None
    return out


def _outcome_from_json(d: Any) -> PickOutcome:
    if not isinstance(d, dict):
        raise TypeError("not an object")
    v = d.get("v")
    if v != SIDECAR_VERSION:
        raise ValueError(f"sidecar version {v!r}; this boxloc reads version {SIDECAR_VERSION}")
    scan, surface, ok = d["scan"], d["surface"], d["ok"]
    if not (isinstance(scan, int) and isinstance(surface, int) and isinstance(ok, bool)):
        raise TypeError("scan and surface must be integers, ok a boolean")
    return PickOutcome(scan_index=scan, surface_id=surface, ok=ok,
                       reason=str(d.get("reason", ""))[:MAX_REASON],
                       source=str(d.get("source", ""))[:100],
                       wall_time_ns=int(d.get("wall_time_ns", 0)), origin="sidecar")


def latest_outcomes(outcomes: list[PickOutcome]) -> dict[tuple[int, int], PickOutcome]:
    """The last reported outcome of each (scan, surface), by wall time then report order."""
    out: dict[tuple[int, int], PickOutcome] = {}
    for o in sorted(enumerate(outcomes), key=lambda io: (io[1].wall_time_ns, io[0])):
        out[(o[1].scan_index, o[1].surface_id)] = o[1]
    return out

"""What every scan-file case shares: reading (``read_scan``, ``read_labels``) and the round
trip through a log, adversarial arrays, and the reader options.
"""

from __future__ import annotations

import contextlib
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from recorder.fuzz.cases import Job, Step, _pick


def _roundtrip(scan: Any, d: Path) -> None:
    """Record a scan that read and read it back: it must come back bit for bit."""
    from recorder.mcap.log import open_log
    from recorder.mcap.sink import McapRecorder

    p = d / "roundtrip.mcap"
    with contextlib.suppress(FileNotFoundError):
        p.unlink()
    with McapRecorder(p, fsync=False, max_points=200, session="fuzz") as rec:
        rec.record_scan(scan)
    back = list(open_log(p).scans())
    if len(back) != 1 or back[0].scan.range.tobytes() != scan.range.tobytes() \
            or back[0].scan.capture_time_ns != scan.capture_time_ns:
        raise AssertionError("a scan that read does not come back from its log bit for bit")


def scan_file_steps(path: Path, kw: dict[str, Any], d: Path, *, labels: bool = False
                    ) -> list[Step]:
    """Read a scan file (``read_scan(path, **kw)``), then record the scan and read it back."""

    def read() -> None:
        from boxloc.io import read_scan

        scan = read_scan(path, **kw)
        _ = (scan.points, scan.seed, scan.up)
        _roundtrip(scan, d)

    steps: list[Step] = [("read_scan", read)]
    if labels:
        def read_labels() -> None:
            from boxloc.io import read_labels as rl

            rl(path)

        steps.append(("read_labels", read_labels))
    return steps


def _file_job(kind: str, path: Path, kw: dict[str, Any], d: Path, *, labels: bool = False
              ) -> Job:
    return Job(kind, scan_file_steps(path, kw, d, labels=labels), dict(kw))


def _storm(rng: np.random.Generator, shape: tuple[int, ...], dtype: Any = np.float32
           ) -> tuple[np.ndarray, str]:
    """A float array of ``shape`` full of trouble (or of plausible ranges)."""
    kind = str(_pick(rng, ["nan", "mostly-nan", "inf", "-inf", "mixed", "negative", "zeros",
                           "huge", "subnormal", "const", "random", "plausible"]))
    n = int(np.prod(shape)) if shape else 1
    base = rng.uniform(0.5, 3.0, n)
    if kind == "nan":
        a = np.full(n, np.nan)
    elif kind == "mostly-nan":
        a = np.where(rng.random(n) < 0.99, np.nan, base)
    elif kind == "inf":
        a = np.full(n, np.inf)
    elif kind == "-inf":
        a = np.where(rng.random(n) < 0.5, -np.inf, base)
    elif kind == "mixed":
        a = rng.choice([np.nan, np.inf, -np.inf, 0.0, -0.0, 1.0, 1e38, -1e-45], n)
    elif kind == "negative":
        a = -base
    elif kind == "zeros":
        a = np.zeros(n)
    elif kind == "huge":
        a = np.full(n, 3.0e38) * rng.choice([1.0, 10.0], n)
    elif kind == "subnormal":
        a = np.full(n, 1e-45)
    elif kind == "const":
        a = np.full(n, 1.5)
    elif kind == "random":
        a = rng.normal(0, 1e3, n)
    else:
        a = base
    with np.errstate(over="ignore", invalid="ignore"):
        return a.reshape(shape).astype(dtype), kind


_SHAPES_2D = ((0, 0), (0, 5), (5, 0), (1, 1), (1, 40), (40, 1), (3, 4), (36, 48), (48, 36))


def _adv_array(rng: np.random.Generator, ndim: int, last: int | None = None
               ) -> tuple[np.ndarray, str]:
    """An adversarial array: mostly ``ndim``-D, sometimes another rank; dtypes of every
    kind, contents from :func:`_storm`."""
    u = rng.random()
    if u < 0.75:
        shape: tuple[int, ...] = tuple(_SHAPES_2D[int(rng.integers(0, len(_SHAPES_2D)))])
        if ndim == 3:
            shape = (*shape, last or 3)
    else:
        shape = tuple(int(_pick(rng, [0, 1, 2, 3, 5])) for _ in range(int(rng.integers(0, 5))))
    dt = str(_pick(rng, ["float32"] * 6 + ["float64", "float16", "longdouble", ">f4", "int32",
                                           "uint16", "bool", "complex64", "object", "<U3",
                                           "datetime64[ns]"]))
    a, kind = _storm(rng, shape)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if dt == "object":
            a = a.astype(object)
        elif dt == "<U3":
            a = a.astype("<U3")
        elif dt == "datetime64[ns]":
            a = np.zeros(shape, "datetime64[ns]")
        elif dt in ("int32", "uint16", "bool"):
            a = np.nan_to_num(a.astype(np.float64), nan=0, posinf=0, neginf=0).astype(dt)
        else:
            a = _zero_padding(a.astype(dt))
    return a, f"{dt}{list(shape)}:{kind}"


def _zero_padding(a: np.ndarray) -> np.ndarray:
    """``a`` with the padding bytes of x87 extended-precision elements zeroed (in place if
    ``a`` is C-contiguous).

    Such a ``longdouble`` holds 10 bytes of its 16; a cast leaves the other 6 as it found
    the memory, so a file written from it differed from run to run. Other dtypes, and
    platforms whose ``longdouble`` uses every byte, are returned as they are.
    """
    if a.dtype != np.longdouble or np.finfo(np.longdouble).nmant != 63 or a.size == 0:
        return a
    if not a.flags.c_contiguous:  # (np.ascontiguousarray would make a 0-d array 1-d)
        a = a.copy(order="C")
    a.reshape(-1).view(np.uint8).reshape(a.size, a.itemsize)[:, 10:] = 0
    return a


_BAD_INTRINSICS = ("nan,1,2,3", "0,0,0,0", "1,2,3", "inf,1,1,1", "-1,1,1,1", "a,b,c,d",
                   "1e309,1,1,1", "", "1,1,1,1,1", "1e-300,1e-300,0,0")


def _intrinsics_kw(rng: np.random.Generator, corpus: dict[str, Any]) -> Any:
    u = rng.random()
    if u < 0.45:
        return None
    if u < 0.85:
        return corpus["intrinsics"]
    return str(_pick(rng, _BAD_INTRINSICS))

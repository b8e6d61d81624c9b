"""Fuzzing the readers: mutated logs, mutated and adversarial scan files, degenerate scans.

Every case is one bad (or odd) input handed to the code that reads untrusted data:

``log-bytes``
    A log (the repository's sample logs, or small logs made here) with its bytes mutated:
    truncated, bits flipped, spans overwritten, inserted, deleted, duplicated or zeroed,
    two logs spliced, a record's length or opcode changed, a chunk's content mutated with
    its CRC fixed (so the records inside reach the parsers), or its pick-outcome sidecar
    mutated.
``log-records``
    A small log rewritten as a *valid* MCAP file whose content is hostile: a message's
    protobuf fields (array shapes, dtypes, filters, names, data, record versions, image
    sizes), the ``boxloc.run`` metadata (config and sensor JSON), attachment names, channel
    topics, message order and sequence numbers.
``npz``, ``image``, ``cloud``
    Scan files: ``.npz`` with adversarial arrays (NaN and inf storms, zero sizes, absurd
    shapes declared in the ``.npy`` header, int, complex, object, bool, float16 dtypes),
    PNG/TIFF depth images (adversarial content, headers claiming huge sizes, other formats
    under a depth-image name), organized PCD/PLY clouds (adversarial content and headers),
    and byte mutations of valid files of each format.
``bag``
    ROS 2 bags (:mod:`boxloc.io.rosbag`): a small ``.mcap`` and ``.db3`` bag with their bytes
    mutated, or written valid by ``rosbags`` with hostile messages (image sizes, steps,
    encodings and data lengths that disagree, non-finite or zero intrinsics, distortion,
    unorganized or malformed clouds, degenerate or cyclic /tf). Every frame read is recorded
    and read back bit for bit; a damaged bag must end in one clean error.
``scan``, ``pipeline``
    :class:`boxloc.scan.Scan`, :meth:`~boxloc.scan.Scan.from_points` and the sensor models on
    adversarial arrays, and :func:`boxloc.pipeline.find_graspable_surfaces` (recorded, read
    back and compared bit for bit) on tiny degenerate scans: one valid pixel, all-equal
    range, a single plane, one row, extreme scales.

A log is opened strictly and with ``allow_truncated``, every scan is decoded, it is
recovered with :func:`recorder.mcap.recover.recover_log` and the recovered log read back, and
``boxloc info`` is computed for it. A scan file that reads is recorded to a log and read
back bit for bit.

Each case ends as one of

* ``ok``: handled (read, recovered, localized);
* ``error``: a clean refusal, a :class:`~boxloc.errors.BoxlocError` (``InputError``,
  ``LogError``, ``RecordingError``) with a one-line message;
* ``failure``: anything else: another exception (a crash traceback), a multi-line error
  message, a case that ran longer than ``timeout_s`` (the worker is killed), a worker that
  died, or a case whose peak resident memory grew by more than ``mem_bound_mb`` (measured
  per case from ``VmHWM``, reset through ``/proc/self/clear_refs``; workers also run under
  an address-space limit, so a runaway allocation fails instead of exhausting the machine).

Cases run in worker processes; each case is generated from ``(seed, case index)`` alone, so
a run is reproducible and a case can be regenerated. The input of every failing case is
saved under ``workdir/failures/case-NNNNN/`` with ``case.json`` (what failed, the
traceback); ``python -m recorder.fuzz --case DIR`` runs it again in-process.

Registered as the ``fuzz`` section of ``boxloc bench`` (entry-point group ``boxloc.bench``);
``boxloc bench --fuzz N`` runs only it, with N cases.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import re
import resource
import shutil
import struct
import sys
import tempfile
import time
import traceback
import warnings
import zipfile
import zlib
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from boxloc.errors import BoxlocError

#: The case categories, and the order in which cases cycle through them (weights: how
#: often each appears in 20 consecutive cases).
CATEGORIES: tuple[str, ...] = ("log-bytes", "log-records", "npz", "image", "cloud", "scan",
                               "pipeline", "bag")
_CYCLE: tuple[str, ...] = (
    "log-bytes", "log-records", "npz", "image", "cloud", "scan", "pipeline",
    "log-bytes", "log-records", "npz", "log-bytes", "log-records", "npz", "image",
    "cloud", "scan", "pipeline", "log-bytes", "log-records", "log-bytes", "bag",
)

#: Default per-case wall-time limit, seconds (the worker is killed past it).
DEFAULT_TIMEOUT_S = 30.0
#: Default bound on a case's peak resident-memory growth, MB.
DEFAULT_MEM_BOUND_MB = 512
#: A worker is restarted when its resident memory has grown this much since warm-up, MB.
_RESTART_GROWTH_MB = 1024
#: Failures listed in full in the report (all are saved to disk).
_MAX_LISTED = 50

Step = tuple[str, Callable[[], Any]]


@dataclass(frozen=True)
class Case:
    """One fuzz case: its number, category and the run's seed (the case's generator is
    ``np.random.default_rng([seed, index])``)."""

    index: int
    category: str
    seed: int

    def rng(self) -> np.random.Generator:
        return np.random.default_rng([self.seed, self.index])


@dataclass
class Job:
    """A generated case: what it is (``kind``) and the calls to make (``steps``)."""

    kind: str
    steps: list[Step] = field(default_factory=list)
    #: the reader's keyword arguments, for a file case (saved with a failure)
    read_kw: dict[str, Any] = field(default_factory=dict)


def _pick(rng: np.random.Generator, seq: Sequence[Any]) -> Any:
    """One element of ``seq`` as it is (``rng.choice`` would make big ints floats)."""
    return seq[int(rng.integers(0, len(seq)))]


def plan(n: int, seed: int) -> list[Case]:
    """The ``n`` cases of a run (categories cycle through :data:`_CYCLE`)."""
    return [Case(i, _CYCLE[i % len(_CYCLE)], int(seed)) for i in range(int(n))]


# --- the corpus: valid inputs to mutate ----------------------------------------------------


def default_sample_logs() -> list[Path]:
    """The repository's sample logs (``logs/*.mcap``), if this is a source checkout."""
    import boxloc

    d = Path(boxloc.__file__).resolve().parents[1] / "logs"
    return sorted(d.glob("*.mcap")) if d.is_dir() else []


def build_corpus(d: Path, sample_logs: Sequence[str | os.PathLike[str]] = ()) -> dict[str, Any]:
    """Write the valid inputs the cases mutate into ``d``; return their paths by kind.

    Small logs (two localized scans; a ray-table scan and a failed scan with pick outcomes;
    an imported scan with labels), a small scan as ``.npz`` (full, points only, range
    only), as a 16-bit PNG and a float TIFF depth image, and as organized PCD (ascii,
    binary, binary_compressed) and PLY (ascii, binary) clouds.
    """
    import cv2

    from boxloc.config import Config
    from boxloc.io import write_npz
    from boxloc.pipeline import find_graspable_surfaces
    from boxloc.scan import PinholeModel, RayTableModel, Scan
    from boxloc.simulate import simulate
    from recorder.mcap.sink import McapRecorder

    d.mkdir(parents=True, exist_ok=True)
    cfg = Config()
    small = []
    p = d / "small.mcap"
    with McapRecorder(p, config=cfg, fsync=False, session="fuzz-small", overwrite=True) as rec:
        for i, spec in enumerate(("single:width=80,height=60,f=65.6",
                                  "pallet:width=80,height=60,f=65.6")):
            scan = dataclasses.replace(simulate(spec, seed=i + 1).scan, index=i)
            res = find_graspable_surfaces(scan, cfg, observer=rec)
            if len(res.surfaces):
                rec.record_outcome(i, 0, ok=True)
    small.append(p)
    p = d / "raytable.mcap"
    with McapRecorder(p, config=cfg, fsync=False, session="fuzz-rays", overwrite=True) as rec:
        base = simulate("single:width=64,height=48,f=52.5", seed=5).scan
        rays = base.sensor.rays().copy()
        v, u = np.mgrid[0:48, 0:64]
        rays[..., :2] *= (1.0 + 0.02 * (((u - 32) / 64) ** 2 + ((v - 24) / 48) ** 2))[..., None]
        rays[0, 0] = np.nan
        scan = Scan(range=base.range, sensor=RayTableModel(rays), index=0,
                    sensor_to_base=base.sensor_to_base, capture_time_ns=base.capture_time_ns)
        with contextlib.suppress(BoxlocError):
            find_graspable_surfaces(scan, cfg, observer=rec)
        bad = dataclasses.replace(base, index=1)
        rec.on_scan(bad, cfg)
        rec.on_error(bad, RuntimeError("a failure, recorded"))
    small.append(p)
    p = d / "imported.mcap"
    with McapRecorder(p, config=cfg, fsync=False, session="fuzz-import", overwrite=True) as rec:
        scan = simulate("mixed:width=48,height=36,f=39.4", seed=7).scan
        labels = (np.arange(scan.range.size).reshape(scan.shape) // 97).astype(np.int32)
        rec.record_scan(scan, cfg, labels=labels)
    small.append(p)
    side = d / "small.mcap.outcomes.jsonl"
    side.write_text("".join(json.dumps({"v": 1, "scan": i, "surface": 0, "ok": i % 2 == 0,
                                        "reason": "fuzz", "source": "annotate",
                                        "wall_time_ns": 1_700_000_000_000_000_000 + i}) + "\n"
                            for i in range(2)))

    scan = simulate("single:width=48,height=36,f=39.4", seed=3).scan
    s = scan.sensor
    assert isinstance(s, PinholeModel)  # the simulator's camera
    intr = f"{s.fx!r},{s.fy!r},{s.cx!r},{s.cy!r}"
    npz = [d / "scan.npz", d / "points.npz", d / "range.npz"]
    write_npz(scan, npz[0])
    np.savez(npz[1], points=scan.points)
    np.savez(npz[2], range=scan.range)
    z = scan.points[..., 2].astype(np.float64)
    images = [d / "depth.png", d / "depth.tiff"]
    cv2.imwrite(str(images[0]), np.where(np.isfinite(z), np.round(z * 1000), 0).astype(np.uint16))
    cv2.imwrite(str(images[1]), np.where(np.isfinite(z), z, np.nan).astype(np.float32))
    P = np.asarray(scan.points, np.float32)
    point_labels = (np.arange(P.shape[0] * P.shape[1]) % 7).astype(np.uint32).reshape(
        P.shape[:2])
    clouds = []
    for kind in ("ascii", "binary", "binary_compressed"):
        q = d / f"cloud-{kind}.pcd"
        q.write_bytes(pcd_bytes(P, kind, labels=point_labels))
        clouds.append(q)
    for fmt in ("ascii", "binary_little_endian"):
        q = d / f"cloud-{fmt}.ply"
        q.write_bytes(ply_bytes(P, fmt, labels=point_labels))
        clouds.append(q)
    from boxloc.io.rosbag import write_depth_bag

    bag_scans = [simulate("single:width=48,height=36,f=39.4", seed=k).scan for k in (3, 4)]
    for name in ("bag.mcap", "bag.db3", "cloud.mcap"):  # a writer never overwrites
        (d / name).unlink(missing_ok=True)
    bags = [write_depth_bag(d / "bag.mcap", bag_scans, single_file=True),
            write_depth_bag(d / "bag.db3", bag_scans, storage="sqlite3", encoding="32FC1",
                            single_file=True),
            write_depth_bag(d / "cloud.mcap", bag_scans[:1], encoding="cloud",
                            single_file=True)]
    # Copies: the originals may be regenerated while a long run reads them.
    logs: list[Path] = []
    for x in sample_logs:
        if Path(x).is_file():
            logs.append(d / f"sample-{len(logs)}-{Path(x).name}")
            shutil.copyfile(x, logs[-1])
    return {
        "small_logs": [str(x) for x in small],
        "logs": [str(x) for x in small + logs],
        "sidecar": str(side),
        "npz": [str(x) for x in npz],
        "images": [str(x) for x in images],
        "clouds": [str(x) for x in clouds],
        "intrinsics": intr,
        "depth_scale": 0.001,
        "bags": [str(x) for x in bags],
    }


def _lzf_literal(data: bytes) -> bytes:
    """LZF stream of literal runs only (valid LZF, no compression), for PCD
    ``binary_compressed``."""
    out = bytearray()
    for i in range(0, len(data), 32):
        chunk = data[i:i + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def _xyz_records(P: np.ndarray, labels: np.ndarray | None, byte_order: str, label_type: str
                 ) -> tuple[np.ndarray, list[tuple[str, str]]]:
    """The (H, W, 3) cloud ``P`` (and optional labels) as one flat record array, with its
    fields: float32 x, y, z and ``label`` of ``label_type``, in ``byte_order``."""
    fields = [(c, byte_order + "f4") for c in "xyz"]
    if labels is not None:
        fields.append(("label", byte_order + label_type))
    rec = np.zeros(P.shape[0] * P.shape[1], dtype=fields)
    flat = P.reshape(-1, 3)
    for i, c in enumerate("xyz"):
        rec[c] = flat[:, i]
    if labels is not None:
        rec["label"] = labels.reshape(-1)
    return rec, fields


def pcd_bytes(P: np.ndarray, data: str, *, labels: np.ndarray | None = None,
              header: dict[str, str] | None = None) -> bytes:
    """An organized PCD file of the (H, W, 3) float32 cloud ``P`` (``data``: ascii, binary or
    binary_compressed), optionally with a uint32 ``label`` field; ``header`` overrides
    header lines by key."""
    H, W = P.shape[:2]
    n = H * W
    rec, fields = _xyz_records(P, labels, "<", "u4")
    head = {
        "VERSION": "0.7", "FIELDS": " ".join(f for f, _ in fields),
        "SIZE": " ".join("4" for _ in fields),
        "TYPE": " ".join("U" if f == "label" else "F" for f, _ in fields),
        "COUNT": " ".join("1" for _ in fields), "WIDTH": str(W), "HEIGHT": str(H),
        "VIEWPOINT": "0 0 0 1 0 0 0", "POINTS": str(n), "DATA": data,
    }
    head.update(header or {})
    text = "# .PCD v0.7 - fuzz\n" + "".join(f"{k} {v}\n" for k, v in head.items())
    if data == "ascii":
        body = "".join(" ".join(repr(float(v)) if isinstance(v, float) else str(int(v))
                                for v in row) + "\n" for row in rec.tolist()).encode()
    elif data == "binary_compressed":
        cols = b"".join(np.ascontiguousarray(rec[f]).tobytes() for f, _ in fields)
        comp = _lzf_literal(cols)
        body = struct.pack("<II", len(comp), len(cols)) + comp
    else:
        body = rec.tobytes()
    return text.encode() + body


def ply_bytes(P: np.ndarray, fmt: str, *, labels: np.ndarray | None = None,
              header_lines: list[str] | None = None) -> bytes:
    """An organized PLY (``obj_info num_cols/num_rows``) of the (H, W, 3) cloud ``P``."""
    H, W = P.shape[:2]
    n = H * W
    bo = ">" if fmt == "binary_big_endian" else "<"
    rec, _ = _xyz_records(P, labels, bo, "i4")
    lines = header_lines or [
        f"format {fmt} 1.0", f"obj_info num_cols {W}", f"obj_info num_rows {H}",
        f"element vertex {n}", "property float x", "property float y", "property float z",
    ] + (["property int label"] if labels is not None else [])
    head = "ply\n" + "".join(ln + "\n" for ln in lines) + "end_header\n"
    if fmt == "ascii":
        body = "".join(" ".join(repr(float(v)) if isinstance(v, float) else str(int(v))
                                for v in row) + "\n" for row in rec.tolist()).encode()
    else:
        body = rec.tobytes()
    return head.encode() + body


# --- byte mutations --------------------------------------------------------------------------

_INTERESTING = (0, 1, 2, 3, 7, 255, 256, 65535, 2**31 - 1, 2**31, 2**32 - 1, 2**32, 2**53,
                2**62, 2**63 - 1, 2**63, 2**64 - 1)
_BYTE_OPS = ("truncate", "flip", "overwrite", "insert", "delete", "duplicate", "zero",
             "splice", "ints")


def mutate_bytes(rng: np.random.Generator, data: bytes, other: bytes | None = None,
                 op: str | None = None) -> tuple[bytes, str]:
    """One random byte-level mutation of ``data``; returns ``(mutated, op)``."""
    op = op or str(_pick(rng, _BYTE_OPS))
    n = len(data)
    if n == 0:
        return bytes(rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8)), "random"
    b = bytearray(data)
    at = int(rng.integers(0, n))
    span = min(n - at, int(rng.integers(1, 1 + max(1, min(4096, n // 4)))))
    if op == "truncate":
        # Anywhere, but often near the end (inside the summary) or near the start.
        where = rng.random()
        cut = (int(rng.integers(max(0, n - 4096), n)) if where < 0.3 else
               int(rng.integers(0, min(n, 256))) if where < 0.4 else at)
        return bytes(b[:cut]), op
    if op == "flip":
        for _ in range(int(rng.integers(1, 17))):
            i = int(rng.integers(0, n))
            b[i] ^= 1 << int(rng.integers(0, 8))
        return bytes(b), op
    if op == "overwrite":
        b[at:at + span] = rng.integers(0, 256, span, dtype=np.uint8).tobytes()
        return bytes(b), op
    if op == "insert":
        k = int(rng.integers(1, 512))
        return bytes(b[:at]) + rng.integers(0, 256, k, dtype=np.uint8).tobytes() + bytes(
            b[at:]), op
    if op == "delete":
        del b[at:at + span]
        return bytes(b), op
    if op == "duplicate":
        seg = bytes(b[at:at + span])
        j = int(rng.integers(0, n))
        return bytes(b[:j]) + seg + bytes(b[j:]), op
    if op == "zero":
        b[at:at + span] = bytes(span)
        return bytes(b), op
    if op == "splice" and other:
        j = int(rng.integers(0, len(other)))
        return bytes(b[:at]) + other[j:], op
    # "ints" (and splice without a partner): an interesting integer over 1-8 bytes
    width = int(_pick(rng, [1, 2, 4, 8]))
    v = int(_pick(rng, _INTERESTING)) & ((1 << (8 * width)) - 1)
    b[at:at + width] = v.to_bytes(width, "little")[: n - at]
    return bytes(b[:n]), "ints"


def _records(data: bytes) -> list[tuple[int, int, int]]:
    """Top-level MCAP record framing ``(offset, opcode, length)`` after the magic."""
    out = []
    off = 8
    while off + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, off)
        if off + 9 + length > len(data):
            break
        out.append((off, opcode, length))
        off += 9 + length
    return out


def _mutate_record_frame(rng: np.random.Generator, data: bytes) -> tuple[bytes, str]:
    recs = _records(data)
    if not recs:
        return mutate_bytes(rng, data, op="flip")
    off, opcode, length = recs[int(rng.integers(0, len(recs)))]
    b = bytearray(data)
    u = rng.random()
    if u < 0.3:
        return data[:off] + _random_record(rng) + data[off:], "record-insert"
    if u < 0.7:
        choices = [0, 1, 8, max(0, length - 1), length + 1, len(data), 2 * len(data),
                   *_INTERESTING]
        new = int(_pick(rng, choices)) & (2**64 - 1)
        b[off + 1:off + 9] = struct.pack("<Q", new)
        return bytes(b), "record-length"
    b[off] = int(_pick(rng, [0x00, 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x09, 0x0A,
                             0x0B, 0x0C, 0x0D, 0x0E, 0x0F, 0x10, 0x7F, 0xFF]))
    return bytes(b), "record-opcode"


def _random_record(rng: np.random.Generator) -> bytes:
    """A record of a random (mostly known) opcode with a short random body: it parses as
    far as the body goes."""
    op = int(_pick(rng, [0x01, 0x02, 0x03, 0x04, 0x05, 0x05, 0x05, 0x06, 0x07, 0x08, 0x09,
                         0x0A, 0x0B, 0x0C, 0x0D, 0x0E, 0x0F, 0x80]))
    body = rng.integers(0, 256, int(rng.integers(0, 48)), dtype=np.uint8).tobytes()
    if rng.random() < 0.3:  # plausible small length prefixes inside
        body = bytes(8) + body
    return struct.pack("<BQ", op, len(body)) + body


def _mutate_chunk_content(rng: np.random.Generator, data: bytes) -> tuple[bytes, str]:
    """Mutate the records inside a chunk, then fix its CRC and sizes, so that the damage
    passes the CRC check and reaches the record parsers."""
    import zstandard

    chunks = [r for r in _records(data) if r[1] == 0x06]
    if not chunks:
        return mutate_bytes(rng, data, op="flip")
    off, _, length = chunks[int(rng.integers(0, len(chunks)))]
    body = data[off + 9:off + 9 + length]
    try:
        t0, t1, _usize, _crc = struct.unpack_from("<QQQI", body, 0)
        (clen,) = struct.unpack_from("<I", body, 28)
        comp = body[32:32 + clen]
        (dlen,) = struct.unpack_from("<Q", body, 32 + clen)
        payload = body[40 + clen:40 + clen + dlen]
        inner = zstandard.decompress(payload) if comp == b"zstd" else payload
    except (struct.error, zstandard.ZstdError):
        return mutate_bytes(rng, data, op="flip")
    if rng.random() < 0.4:
        new_inner, what = _mutate_inner_frame(rng, inner)
    else:
        new_inner, what = mutate_bytes(rng, inner)
    packed = zstandard.compress(new_inner) if comp == b"zstd" else new_inner
    new_body = (struct.pack("<QQQI", t0, t1, len(new_inner), zlib.crc32(new_inner))
                + struct.pack("<I", len(comp)) + comp + struct.pack("<Q", len(packed))
                + packed)
    rec = struct.pack("<BQ", 0x06, len(new_body)) + new_body
    return data[:off] + rec + data[off + 9 + length:], f"chunk-{what}"


def _mutate_inner_frame(rng: np.random.Generator, inner: bytes) -> tuple[bytes, str]:
    """Change the opcode or length of one record inside decompressed chunk data."""
    recs = []
    off = 0
    while off + 9 <= len(inner):
        opcode, length = struct.unpack_from("<BQ", inner, off)
        recs.append((off, opcode, length))
        if off + 9 + length > len(inner):
            break
        off += 9 + length
    if not recs:
        return mutate_bytes(rng, inner)
    off, _, length = recs[int(rng.integers(0, len(recs)))]
    b = bytearray(inner)
    u = rng.random()
    if u < 0.3:
        return inner[:off] + _random_record(rng) + inner[off:], "inner-insert"
    if u < 0.65:
        new = int(_pick(rng, [0, 1, 4, 21, 22, max(0, length - 1), length + 1,
                              *_INTERESTING])) & (2**64 - 1)
        b[off + 1:off + 9] = struct.pack("<Q", new)
        return bytes(b), "inner-length"
    b[off] = int(_pick(rng, [0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x09, 0x0F, 0xFF]))
    return bytes(b), "inner-opcode"


# --- log cases -------------------------------------------------------------------------------


def _drain(log: Any) -> None:
    """Touch everything a reader of a log can be asked for."""
    _ = (log.run, log.version, log.config)
    for a in log.attachments():
        log.attachment(a.name)
    for rec in log.scans():
        _ = (rec.scan.points, rec.scan.seed, rec.result, rec.tests, rec.surfaces)
    log.index()
    log.channels()
    log.time_span()
    log.outcomes()
    log.latest_outcomes()


def log_steps(path: Path, d: Path) -> list[Step]:
    """The reader calls a log case makes (see the module docstring)."""

    def strict() -> None:
        from recorder.mcap.log import open_log

        _drain(open_log(path))

    def lenient() -> None:
        from recorder.mcap.log import open_log

        _drain(open_log(path, allow_truncated=True))

    def recover() -> None:
        from boxloc.errors import LogError
        from recorder.mcap.log import open_log
        from recorder.mcap.recover import recover_log

        rep = recover_log(path, d / "recovered.mcap", overwrite=True)
        try:
            log = open_log(rep.output)
        except LogError as e:  # recovery must always write a complete, readable log
            raise AssertionError(f"recover_log wrote a log that does not open: {e}") from None
        _drain(log)

    def info() -> None:
        from recorder.commands import _print_info, log_info

        data = log_info(path)
        json.dumps(data)
        with contextlib.redirect_stdout(io.StringIO()):
            _print_info(data)  # what `boxloc info` prints, Rich markup and all

    return [("open_log", strict), ("open_log(allow_truncated)", lenient),
            ("recover_log", recover), ("log_info", info)]


def _gen_log_bytes(rng: np.random.Generator, corpus: dict[str, Any], d: Path) -> Job:
    small, logs = corpus["small_logs"], corpus["logs"]
    pool = small if rng.random() < 0.7 else logs
    base = Path(pool[int(rng.integers(0, len(pool)))])
    data = base.read_bytes()
    out = d / "fuzzed.mcap"
    u = rng.random()
    if u < 0.05:
        tiny = [b"", b"\x89MCAP0\r\n", b"\x89MCAP0\r\n" + bytes(9),
                b"\x89MCAP0\r\n\x01" + struct.pack("<Q", 2**63), data[:8] + data[-8:],
                b"not a log at all\n", data[:30]]
        new, what = tiny[int(rng.integers(0, len(tiny)))], "tiny"
    elif u < 0.15:
        new, what = _mutate_record_frame(rng, data)
    elif u < 0.40:
        new, what = _mutate_chunk_content(rng, data)
    elif u < 0.47:
        side = Path(corpus["sidecar"]).read_bytes()
        mutated, op = mutate_bytes(rng, side)
        if rng.random() < 0.5:
            lines = [b'{"v": 1, "scan": 0, "surface": 0, "ok": "yes"}',
                     b'{"v": 2, "scan": 0, "surface": 0, "ok": true}',
                     b'{"v": 1, "scan": -5, "surface": 1e400, "ok": true}',
                     b"[" * 100_000 + b"]" * 100_000, b"null", b'{"v": 1}',
                     b'{"v": 1, "scan": 0, "surface": 0, "ok": true, "wall_time_ns": "x"}',
                     b'{"v": 1, "scan": 0, "surface": 0, "ok": true, "reason": '
                     + b'"' + b"r" * 10_000 + b'"}']
            mutated = side + lines[int(rng.integers(0, len(lines)))] + b"\n"
            op = "line"
        out.write_bytes(Path(corpus["small_logs"][0]).read_bytes())
        Path(str(out) + ".outcomes.jsonl").write_bytes(mutated)
        return Job(f"sidecar-{op}", log_steps(out, d))
    else:
        other = Path(logs[int(rng.integers(0, len(logs)))]).read_bytes()
        new, what = mutate_bytes(rng, data, other)
    out.write_bytes(new)
    return Job(what, log_steps(out, d))


@dataclass
class LogModel:
    """A log as plain data, to be mutated and written back as valid MCAP."""

    library: str
    metadata: list[tuple[str, dict[str, str]]]
    attachments: list[list[Any]]  # [create_time, log_time, name, media_type, data]
    messages: list[dict[str, Any]]


_LOG_CACHE: dict[str, LogModel] = {}


def read_log_model(path: str | os.PathLike[str]) -> LogModel:
    """A (valid) log as a :class:`LogModel`: header library, metadata, attachments and
    messages in file order (each a dict: topic, encoding, ch_meta, schema, log_time,
    publish_time, sequence, data). Cached per path; a fresh copy is returned."""
    path = str(path)
    if path not in _LOG_CACHE:
        from mcap.reader import make_reader

        with open(path, "rb") as f:
            r = make_reader(f)
            hdr = r.get_header()
            msgs = []
            for sch, ch, m in r.iter_messages(log_time_order=False):
                msgs.append({
                    "topic": ch.topic, "encoding": ch.message_encoding,
                    "ch_meta": dict(ch.metadata),
                    "schema": (sch.name, sch.encoding, sch.data) if sch else ("", "", b""),
                    "log_time": m.log_time, "publish_time": m.publish_time,
                    "sequence": m.sequence, "data": m.data})
            md = [(m.name, dict(m.metadata)) for m in r.iter_metadata()]
            att = [[a.create_time, a.log_time, a.name, a.media_type, a.data]
                   for a in r.iter_attachments()]
        _LOG_CACHE[path] = LogModel(hdr.library, md, att, msgs)
    cached = _LOG_CACHE[path]
    return LogModel(cached.library, [(n, dict(v)) for n, v in cached.metadata],
                    [list(a) for a in cached.attachments], [dict(x) for x in cached.messages])


def write_log_model(m: LogModel, path: Path) -> None:
    """Write a :class:`LogModel` as a valid MCAP file (whatever its content)."""
    from mcap.writer import CompressionType, Writer

    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(library=m.library)
        for name, md in m.metadata:
            w.add_metadata(name, md)
        for ct, lt, name, mt, data in m.attachments:
            w.add_attachment(ct, lt, name, mt, data)
        schemas: dict[tuple[str, str, bytes], int] = {}
        chans: dict[tuple[str, str, int, str], int] = {}
        for x in m.messages:
            key = x["schema"]
            if key not in schemas:
                schemas[key] = w.register_schema(*key) if key[0] or key[1] else 0
            sid = schemas[key]
            ckey = (x["topic"], x["encoding"], sid, json.dumps(x["ch_meta"], sort_keys=True))
            if ckey not in chans:
                chans[ckey] = w.register_channel(x["topic"], x["encoding"], sid, x["ch_meta"])
            w.add_message(chans[ckey], x["log_time"], x["data"], x["publish_time"],
                          x["sequence"])
        w.finish()


_BAD_NAMES = ("", "../../../../tmp/boxloc-fuzz-escape", "/tmp/boxloc-fuzz-abs", "a\x00b",
              "x" * 5000, "..", ".", "nested/../../up", "C:\\windows\\evil", "\u202etxt.exe",
              "config.toml", "tests/kind", "[/]", "[bold red]x", "[link=file:///etc/passwd]x")
_BAD_DTYPES = ("|O", "<c16", "<f2", "|b1", "<i8", ">f8", "<M8[ns]", "|V8", "|U0", "<U0",
               "|S4", "<U999999", "", "garbage", "<f4", "<u8", "|u1", "<f16", "<U1")
_BAD_JSON = ("", "{", "[]", "null", "1e999", '{"alpha": "x"}', '{"noise": "abc"}',
             '{"noise": [1, 2]}', '{"noise": {"sigma0": "a"}}', '{"workers": 1e300}',
             '{"max_pixels": -1}', '{"alpha": NaN}', '{"kind": "pinhole", "fx": "nan"}',
             '{"kind": "raytable"}', "[" * 50_000 + "]" * 50_000, "[/]", "[bold]",
             '{"a":' * 20_000 + "1" + "}" * 20_000, '"\\ud800"')


def _deep_json() -> str:
    return "[" * 100_000 + "]" * 100_000


def _mutate_product(rng: np.random.Generator, data: bytes) -> tuple[bytes, str]:
    from recorder.mcap.proto import message_class

    msg = message_class("Product")()
    try:
        msg.ParseFromString(data)
    except Exception:  # noqa: BLE001 - then mutate the bytes instead
        return mutate_bytes(rng, data)
    arrays = list(msg.arrays)
    what = str(_pick(rng, ["shape", "dtype", "filter", "name", "data", "schema", "drop",
                           "duplicate", "string", "index"]))
    if what == "schema":
        msg.schema = str(_pick(rng, [msg.schema.replace("/1.", "/2."), "boxloc.Other/1.0", "",
                                     "x" * 1000, re.sub(r"/1\.\d+$", "/1.99", msg.schema),
                                     re.sub(r"/1\.\d+$", "/0.9", msg.schema)]))
    elif what == "index":
        msg.scan_index = int(_pick(rng, [-1, 2**63 - 1, -(2**63), 7]))
    elif not arrays:
        return mutate_bytes(rng, data)
    else:
        a = arrays[int(rng.integers(0, len(arrays)))]
        if what == "shape":
            nd = int(_pick(rng, [0, 1, 2, 2, 3, 3, 9, 40]))
            del a.shape[:]
            a.shape.extend(0 if rng.random() < 0.3 else int(_pick(rng, _INTERESTING))
                           for _ in range(nd))
            if rng.random() < 0.3:
                a.data = b""
        elif what == "dtype":
            a.dtype = str(_pick(rng, _BAD_DTYPES))
            if rng.random() < 0.3:
                a.data = b""
                del a.shape[:]
                a.shape.extend([0] if rng.random() < 0.5 else [])
        elif what == "filter":
            a.filter = int(_pick(rng, [0, 1, 2, 3, 4, 99]))
        elif what == "name":
            a.name = str(_pick(rng, _BAD_NAMES))
        elif what == "data":
            k = int(rng.integers(0, len(a.data) + 2))
            a.data = a.data[:k] if rng.random() < 0.5 else a.data + bytes(k)
        elif what == "drop":
            msg.arrays.remove(a)
        elif what == "duplicate":
            msg.arrays.add().CopyFrom(a)
        elif what == "string":
            s = _deep_json() if rng.random() < 0.5 else str(_pick(rng, _BAD_JSON))
            raw = np.asarray(s)
            a.dtype, a.filter = raw.dtype.str, 0
            del a.shape[:]
            a.data = raw.tobytes()
    return msg.SerializeToString(), f"product-{what}"


def _mutate_image(rng: np.random.Generator, data: bytes) -> tuple[bytes, str]:
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    msg = RawImage()
    try:
        msg.ParseFromString(data)
    except Exception:  # noqa: BLE001
        return mutate_bytes(rng, data)
    what = str(_pick(rng, ["size", "step", "encoding", "data"]))
    big = [0, 1, 100_000, 2**31 - 1, 2**32 - 1, 65536]
    if what == "size":
        msg.width, msg.height = int(_pick(rng, big)), int(_pick(rng, big))
        msg.step = msg.width * 4 % 2**32
    elif what == "step":
        msg.step = int(_pick(rng, big))
    elif what == "encoding":
        msg.encoding = str(_pick(rng, ["16UC1", "", "32FC3", "x" * 100]))
    else:
        k = int(rng.integers(0, len(msg.data) + 1))
        msg.data = msg.data[:k]
    return msg.SerializeToString(), f"image-{what}"


def _mutate_rows(rng: np.random.Generator, data: bytes, topic: str) -> tuple[bytes, str]:
    from recorder.mcap.proto import message_class

    name = {"/boxloc/tests": "TestRows", "/boxloc/timing": "Timing",
            "/boxloc/error": "ScanError", "/pick/outcome": "PickOutcome"}[topic]
    msg = message_class(name)()
    try:
        msg.ParseFromString(data)
    except Exception:  # noqa: BLE001
        return mutate_bytes(rng, data)
    if rng.random() < 0.3:
        msg.schema = str(_pick(rng, [msg.schema.replace("/1.", "/7."), "", "boxloc.X/1.0"]))
    elif name == "TestRows":
        r = msg.rows.add()
        r.stage = str(_pick(rng, ["edges", "", "x" * 1000, "nonsense", "verification"]))
        r.kind = int(_pick(rng, [-1, 0, 255, 256, 2**31 - 1]))
        r.a, r.b = int(_pick(rng, [-(2**63), 2**63 - 1, 0])), -1
        r.statistic = float(_pick(rng, [np.nan, np.inf, -np.inf, 0.0]))
    elif name == "Timing":
        s = msg.stages.add()
        s.stage, s.ms = "x" * int(rng.integers(0, 5000)), float("nan")
    elif name == "ScanError":
        msg.stage = str(_pick(rng, ["\x00" * 10, "[/]", "[bold]"]))
        msg.message = str(_pick(rng, ["line one\nline two", "[/]", "x" * 5000]))
    else:
        msg.surface_id = int(_pick(rng, [-1, 2**31 - 1]))
        msg.scan_index = int(_pick(rng, [-1, 2**63 - 1]))
    return msg.SerializeToString(), f"{name}-fields"


_PRODUCT_TOPICS = ("/scan/sensor", "/scan/info", "/boxloc/edges", "/boxloc/lines",
                   "/boxloc/vertices", "/boxloc/hypotheses", "/boxloc/verification",
                   "/boxloc/selection", "/boxloc/surfaces", "/boxloc/result", "/scan/labels",
                   "/scan/end")


def _gen_log_records(rng: np.random.Generator, corpus: dict[str, Any], d: Path) -> Job:
    small = corpus["small_logs"]
    m = read_log_model(small[int(rng.integers(0, len(small)))])
    what = str(_pick(rng, ["payload"] * 6 + ["metadata", "attachment", "topic", "order"]))
    kind = what
    if what == "payload":
        records = [x for x in m.messages if x["topic"] in _PRODUCT_TOPICS]
        pool = records if records and rng.random() < 0.6 else m.messages
        x = pool[int(rng.integers(0, len(pool)))]
        t = x["topic"]
        if t in _PRODUCT_TOPICS:
            x["data"], kind = _mutate_product(rng, x["data"])
        elif t == "/scan/range":
            x["data"], kind = _mutate_image(rng, x["data"])
        elif t in ("/boxloc/tests", "/boxloc/timing", "/boxloc/error", "/pick/outcome"):
            x["data"], kind = _mutate_rows(rng, x["data"], t)
        else:
            x["data"], kind = mutate_bytes(rng, x["data"])
        kind = f"{t}:{kind}"
    elif what == "metadata":
        name, md = m.metadata[0] if m.metadata else ("boxloc.run", {})
        key = str(_pick(rng, ["config", "sensor", "session", "boxloc_version", "new", "host",
                              "git_commit", "git_dirty", "created_utc", "part"]))
        md[key] = _deep_json() if rng.random() < 0.2 else str(_pick(rng, _BAD_JSON))
        m.metadata[0:1] = [(name, md)]
        if rng.random() < 0.2:
            m.metadata.append((str(_pick(rng, _BAD_NAMES)), {"k": "v"}))
        kind = f"metadata-{key}"
    elif what == "attachment":
        for a in m.attachments:
            if rng.random() < 0.7:
                a[2] = str(_pick(rng, _BAD_NAMES))
            if rng.random() < 0.3:
                a[4] = mutate_bytes(rng, a[4])[0]
        m.attachments.append([0, 0, str(_pick(rng, _BAD_NAMES)), "application/octet-stream",
                              b"payload"])
    elif what == "topic":
        x = m.messages[int(rng.integers(0, len(m.messages)))]
        topics = sorted({y["topic"] for y in m.messages})
        for y in m.messages:
            if y["topic"] == x["topic"]:
                y["topic"] = (str(_pick(rng, topics)) if rng.random() < 0.5
                              else str(_pick(rng, _BAD_NAMES)))
                if rng.random() < 0.3:
                    y["encoding"] = str(_pick(rng, ["json", "cdr", ""]))
    else:
        op = str(_pick(rng, ["drop", "duplicate", "swap", "reverse", "sequence", "time"]))
        i = int(rng.integers(0, len(m.messages)))
        j = int(rng.integers(0, len(m.messages)))
        if op == "drop":
            del m.messages[i]
        elif op == "duplicate":
            m.messages.insert(j, dict(m.messages[i]))
        elif op == "swap":
            m.messages[i], m.messages[j] = m.messages[j], m.messages[i]
        elif op == "reverse":
            m.messages.reverse()
        elif op == "sequence":
            m.messages[i]["sequence"] = int(_pick(rng, [0, 2**32 - 1, 12345]))
        else:
            m.messages[i]["log_time"] = int(_pick(rng, [0, 2**64 - 1, 1]))
        kind = f"order-{op}"
    out = d / "fuzzed.mcap"
    write_log_model(m, out)
    return Job(kind, log_steps(out, d))


# --- scan files ------------------------------------------------------------------------------


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
            a = a.astype(dt)
    return a, f"{dt}{list(shape)}:{kind}"


def _npy_member(descr: str, shape: tuple[int, ...], payload: bytes = b"",
                fortran: bool = False) -> bytes:
    f = io.BytesIO()
    np.lib.format.write_array_header_1_0(f, {"descr": descr, "fortran_order": fortran,
                                             "shape": shape})
    return f.getvalue() + payload


def _write_zip(path: Path, members: dict[str, bytes]) -> None:
    with zipfile.ZipFile(path, "w") as zf:
        for k, v in members.items():
            zf.writestr(k, v)


def _npy(a: np.ndarray) -> bytes:
    f = io.BytesIO()
    np.lib.format.write_array(f, np.asarray(a), allow_pickle=False)
    return f.getvalue()


#: A pickle that would create a file named ``PWNED`` in the working directory if anything
#: ever unpickled it (it is only ever written, as the payload of an ``|O`` npy member).
PICKLE_BOMB = b"cposix\nsystem\n(Vtouch PWNED\ntR."

_BAD_INTRINSICS = ("nan,1,2,3", "0,0,0,0", "1,2,3", "inf,1,1,1", "-1,1,1,1", "a,b,c,d",
                   "1e309,1,1,1", "", "1,1,1,1,1", "1e-300,1e-300,0,0")


def _intrinsics_kw(rng: np.random.Generator, corpus: dict[str, Any]) -> Any:
    u = rng.random()
    if u < 0.45:
        return None
    if u < 0.85:
        return corpus["intrinsics"]
    return str(_pick(rng, _BAD_INTRINSICS))


def _gen_npz(rng: np.random.Generator, corpus: dict[str, Any], d: Path) -> Job:
    p = d / "fuzzed.npz"
    kw: dict[str, Any] = {"intrinsics": _intrinsics_kw(rng, corpus)}
    u = rng.random()
    if u < 0.25:
        src = Path(corpus["npz"][int(rng.integers(0, len(corpus["npz"])))])
        data, op = mutate_bytes(rng, src.read_bytes())
        p.write_bytes(data)
        return _file_job(f"mutate-{op}", p, kw, d)
    with np.load(corpus["npz"][0], allow_pickle=False) as z:
        good = {k: np.array(z[k]) for k in z.files}
    if u < 0.45:
        # A member whose header declares something absurd, with little or no data behind it.
        key = str(_pick(rng, ["range", "points", "intrinsics", "capture_time_ns",
                              "sensor_to_base"]))
        shapes = [(1, 10**9, 3), (10**9, 10**9), (2**62, 2**62), (2**40, 4), (4096, 4097),
                  (-1, 5), (0, 0), (3, 3), (4, 4), (), (1,), (2**63 - 1,), (48, 36),
                  (36, 48, 3), (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17)]
        descrs = ["<f4", "<f8", "|O", "<c16", "|b1", "<f2", "<i8", "<u8", ">f4", "<U4", "|V16",
                  "<M8[ns]", "<f16", "|S3"]
        shape = shapes[int(rng.integers(0, len(shapes)))]
        descr = str(_pick(rng, descrs))
        payload = PICKLE_BOMB if descr == "|O" else bytes(int(_pick(rng, [0, 12, 4096])))
        members = {f"{k}.npy": _npy(v) for k, v in good.items() if k != key}
        members[f"{key}.npy"] = _npy_member(descr, shape, payload,
                                            fortran=bool(rng.random() < 0.2))
        if rng.random() < 0.1:
            members["range.npy"] = b"\x93NUMPY\x01\x00" + struct.pack("<H", 60000) + b"{"
        _write_zip(p, members)
        return _file_job(f"header-{key}:{descr}{list(shape)}", p, kw, d)
    # Adversarial arrays, written the ordinary way.
    keys = [k for k in ("range", "points", "intrinsics", "sensor_to_base", "capture_time_ns")
            if rng.random() < 0.7]
    arrays = {k: good[k] for k in keys if k in good}
    target = str(_pick(rng, ["range", "points", "intrinsics", "sensor_to_base",
                             "capture_time_ns"]))
    if target == "range":
        arrays[target], what = _adv_array(rng, 2)
    elif target == "points":
        arrays[target], what = _adv_array(rng, 3, last=int(_pick(rng, [3, 3, 3, 2, 4])))
    elif target == "intrinsics":
        K = good["intrinsics"].copy()
        opts = [np.full((3, 3), np.nan), np.zeros((3, 3)), -K, K * 1e308, K[:2], np.eye(4),
                K.astype(np.int64), K.astype(np.complex128), K + 1e-3, K[..., None]]
        i = int(rng.integers(0, len(opts)))
        arrays[target], what = opts[i], f"K#{i}"
    elif target == "sensor_to_base":
        opts = [np.full((4, 4), np.nan), np.eye(3), np.eye(4) * 1e308, np.eye(4, dtype=int),
                np.zeros((4, 4)), np.full((4, 4), np.inf), np.eye(4)[None]]
        i = int(rng.integers(0, len(opts)))
        arrays[target], what = opts[i], f"T#{i}"
    else:
        times: list[np.generic | np.ndarray] = [
            np.uint64(2**64 - 1), np.int64(-1), np.float64(1.5), np.int64(2**63 - 1),
            np.zeros((2, 2), np.int64), np.uint64(2**63), np.array("1"), np.int8(-128),
            np.bool_(True)]
        i = int(rng.integers(0, len(times)))
        arrays[target], what = np.asarray(times[i]), f"t#{i}"
    members = {}
    for k, v in arrays.items():
        if v.dtype == object:  # what a careless writer would produce, without the pickle
            members[f"{k}.npy"] = _npy_member("|O", v.shape, PICKLE_BOMB)
        else:
            members[f"{k}.npy"] = _npy(v)
    _write_zip(p, members)
    return _file_job(f"arrays-{target}:{what}", p, kw, d)


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return (struct.pack(">I", len(data)) + kind + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))


def _crafted_image(rng: np.random.Generator) -> tuple[bytes, str, str]:
    """Headers that claim huge (or zero) images, and other formats under a depth-image
    name: (bytes, suffix, what)."""
    dims = [0, 1, 4096, 5000, 65535, 100_000, 2**31 - 1, 2**32 - 1]
    w, h = int(_pick(rng, dims)), int(_pick(rng, dims))
    what = str(_pick(rng, ["png", "tiff", "bigtiff", "ppm", "bmp", "pfm"]))
    if what == "png":
        ihdr = struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0)
        data = (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr)
                + _png_chunk(b"IDAT", zlib.compress(bytes(64))) + _png_chunk(b"IEND", b""))
        return data, ".png", f"png-{w}x{h}"
    if what == "tiff":
        typ = int(_pick(rng, [3, 4, 16, 1]))
        fmt = {3: "H", 4: "I", 16: "I", 1: "B"}[typ]
        ents = [(256, typ, 1, w), (257, typ, 1, h), (258, 3, 1, 32), (259, 3, 1, 1),
                (262, 3, 1, 1), (273, 4, 1, 8), (277, 3, 1, 1), (278, 4, 1, h), (279, 4, 1, 64),
                (339, 3, 1, 3)]
        ifd = struct.pack("<H", len(ents))
        for tag, t, c, v in ents:
            val = struct.pack("<" + fmt, v & (2 ** (8 * struct.calcsize(fmt)) - 1))
            ifd += struct.pack("<HHI", tag, t, c) + val.ljust(4, b"\0")
        ifd += struct.pack("<I", 0)
        off = int(_pick(rng, [8, 8, 8, 2**31, 7]))
        return b"II*\x00" + struct.pack("<I", off) + ifd + bytes(64), ".tiff", \
            f"tiff-t{typ}-{w}x{h}"
    if what == "bigtiff":
        ents = [(256, 16, 1, w), (257, 16, 1, h), (258, 3, 1, 32), (259, 3, 1, 1),
                (262, 3, 1, 1), (273, 16, 1, 16), (277, 3, 1, 1), (278, 16, 1, h),
                (279, 16, 1, 64), (339, 3, 1, 3)]
        ifd = struct.pack("<Q", len(ents))
        for tag, t, c, v in ents:
            ifd += struct.pack("<HHQQ", tag, t, c, v)
        ifd += struct.pack("<Q", 0)
        return b"II+\x00" + struct.pack("<HHQ", 8, 0, 16) + ifd + bytes(64), ".tif", \
            f"bigtiff-{w}x{h}"
    if what == "ppm":
        return f"P5\n{w} {h}\n65535\n".encode() + bytes(64), ".png", f"ppm-{w}x{h}"
    if what == "pfm":
        return f"Pf\n{w} {h}\n-1.0\n".encode() + bytes(64), ".tiff", f"pfm-{w}x{h}"
    hdr = struct.pack("<2sIHHI", b"BM", 54 + 64, 0, 0, 54) + struct.pack(
        "<IiiHHIIiiII", 40, w % 2**31, h % 2**31, 1, 24, 0, 0, 2835, 2835, 0, 0)
    return hdr + bytes(64), ".png", f"bmp-{w}x{h}"


def _scale_kw(rng: np.random.Generator, default: float | None) -> float | None:
    u = rng.random()
    if u < 0.8:
        return default
    return float(_pick(rng, [0.0, -1.0, float("nan"), float("inf"), 1e-300, 1e300, 1.0]))


def _gen_image(rng: np.random.Generator, corpus: dict[str, Any], d: Path) -> Job:
    import cv2

    intr = corpus["intrinsics"] if rng.random() < 0.85 else _intrinsics_kw(rng, corpus)
    u = rng.random()
    if u < 0.3:
        src = Path(corpus["images"][int(rng.integers(0, len(corpus["images"])))])
        data, op = mutate_bytes(rng, src.read_bytes())
        p = d / f"fuzzed{src.suffix}"
        p.write_bytes(data)
        scale = _scale_kw(rng, 0.001 if src.suffix == ".png" else None)
        return _file_job(f"mutate-{op}", p, {"intrinsics": intr, "depth_scale": scale}, d)
    if u < 0.55:
        data, suffix, what = _crafted_image(rng)
        p = d / f"fuzzed{suffix}"
        p.write_bytes(data)
        return _file_job(f"header-{what}", p, {"intrinsics": intr, "depth_scale": 0.001}, d)
    dt = str(_pick(rng, ["uint16", "uint16", "uint8", "float32", "float32", "float64", "int16",
                         "int32"]))
    ch = int(_pick(rng, [1, 1, 1, 3, 4]))
    H, W = (int(_pick(rng, [1, 2, 7, 36])), int(_pick(rng, [1, 3, 48])))
    shape = (H, W) if ch == 1 else (H, W, ch)
    a, kind = _storm(rng, shape, np.float64)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if dt.startswith(("uint", "int")):
            info = np.iinfo(dt)
            a = np.clip(np.nan_to_num(a * 1000, nan=0, posinf=info.max, neginf=info.min),
                        info.min, info.max).astype(dt)
        else:
            a = a.astype(dt)
    suffix = ".png" if dt in ("uint8", "uint16") and rng.random() < 0.6 else str(
        rng.choice([".tiff", ".tif"]))
    p = d / f"fuzzed{suffix}"
    ok = False
    with contextlib.suppress(cv2.error):
        ok = bool(cv2.imwrite(str(p), a))
    if not ok:
        p.write_bytes(b"")
    scale = _scale_kw(rng, 0.001 if dt.startswith("uint") else None)
    return _file_job(f"write-{dt}x{ch}:{kind}", p, {"intrinsics": intr, "depth_scale": scale},
                     d)


_PCD_VALUES = ("0", "-1", "1", "3", "1e9", "nan", "", "abc", "99999999999999999999", "4097",
               "16777217", "2.5")


def _gen_cloud(rng: np.random.Generator, corpus: dict[str, Any], d: Path) -> Job:
    kw = {"intrinsics": _intrinsics_kw(rng, corpus) if rng.random() < 0.3 else None}
    u = rng.random()
    if u < 0.3:
        src = Path(corpus["clouds"][int(rng.integers(0, len(corpus["clouds"])))])
        data, op = mutate_bytes(rng, src.read_bytes())
        p = d / f"fuzzed{src.suffix}"
        p.write_bytes(data)
        return _file_job(f"mutate-{op}", p, kw, d, labels=True)
    H, W = int(_pick(rng, [1, 2, 5, 36])), int(_pick(rng, [1, 4, 48]))
    P, kind = _storm(rng, (H, W, 3))
    if rng.random() < 0.3:  # a plausible organized cloud: a plane 1.5 m ahead
        v, uu = np.mgrid[0:H, 0:W].astype(np.float32)
        P = np.stack([(uu - W / 2) * 0.03, (v - H / 2) * 0.03, np.full_like(uu, 1.5)], -1)
        kind = "plane"
    labels = (np.arange(H * W) % 5).astype(np.uint32).reshape(H, W)
    if rng.random() < 0.5:
        data_kind = str(_pick(rng, ["ascii", "binary", "binary_compressed"]))
        header: dict[str, str] = {}
        if u < 0.7:
            key = str(_pick(rng, ["WIDTH", "HEIGHT", "POINTS", "SIZE", "TYPE", "COUNT",
                                  "VIEWPOINT", "DATA", "FIELDS"]))
            vals = {"SIZE": ["4 4 4 4", "8 4 4 4", "0 4 4 4", "4 4 4", "3 4 4 4"],
                    "TYPE": ["F F F U", "I F F U", "F F F F", "X F F U", "F F F"],
                    "COUNT": ["1 1 1 1", "0 1 1 1", "3 1 1 1", "1 1 1 1000000000"],
                    "VIEWPOINT": ["0 0 0 1 0 0 0", "nan 0 0 1 0 0 0", "0 0 0 0 0 0 0", "1 2",
                                  "0 0 0 1e308 1e308 0 0"],
                    "DATA": ["binary_compressed", "binary", "ascii", "lzma", ""],
                    "FIELDS": ["x y z label", "x y label z", "a b c d", "x y z z"]}
            header[key] = str(_pick(rng, vals.get(key, list(_PCD_VALUES))))
            kind += f"-{key}={header[key][:12]}"
        data = pcd_bytes(P, data_kind, labels=labels, header=header)
        p = d / "fuzzed.pcd"
    else:
        fmt = str(_pick(rng, ["ascii", "binary_little_endian", "binary_big_endian"]))
        lines = None
        if u < 0.7:
            lines = [f"format {fmt} 1.0", f"obj_info num_cols {W}", f"obj_info num_rows {H}",
                     f"element vertex {H * W}", "property float x", "property float y",
                     "property float z", "property int label"]
            i = int(rng.integers(0, len(lines)))
            bad = [f"obj_info num_cols {rng.choice(_PCD_VALUES)}",
                   f"element vertex {rng.choice(_PCD_VALUES)}", "property list uchar int x",
                   "property double y", "element camera 1", "format binary_little_endian 2.0",
                   "property float64 z", "element range_grid 3",
                   "property list uint8 int vertex_indices", "comment " + "c" * 70_000,
                   "element face 4000000000", f"element vertex {H * W}"]
            lines[i] = str(_pick(rng, bad))
            kind += f"-line{i}"
        data = ply_bytes(P, fmt, labels=labels, header_lines=lines)
        p = d / "fuzzed.ply"
    p.write_bytes(data)
    return _file_job(f"write-{p.suffix[1:]}:{kind}", p, kw, d, labels=True)


# --- scans and the pipeline in memory --------------------------------------------------------


def _gen_scan(rng: np.random.Generator, corpus: dict[str, Any], d: Path) -> Job:
    from boxloc.scan import PinholeModel, RayTableModel, Scan

    what = str(_pick(rng, ["range", "range", "points", "points", "pinhole", "raytable"]))
    if what == "range":
        a, desc = _adv_array(rng, 2)
        hw = a.shape if a.ndim == 2 and a.shape[0] > 0 and a.shape[1] > 0 else (1, 1)
        if rng.random() < 0.1:
            hw = (hw[0] + 1, hw[1])
        _save(d, "range", a)
        t_ns = int(_pick(rng, [0, 1, 2**62]))

        def make() -> Any:
            return Scan(range=a, sensor=PinholeModel(40.0, 40.0, hw[1] / 2, hw[0] / 2,
                                                     int(hw[1]), int(hw[0])),
                        capture_time_ns=t_ns)
    elif what == "points":
        P, desc = _adv_array(rng, 3, last=int(_pick(rng, [3, 3, 3, 2])))
        _save(d, "points", P)
        K = None if rng.random() < 0.6 else np.array([[40.0, 0, 10], [0, 40, 10], [0, 0, 1]])

        def make() -> Any:
            return Scan.from_points(P, K)
    elif what == "pinhole":
        vals = [np.nan, np.inf, -np.inf, 0.0, -1.0, 1e-300, 1e300, 5.0, 40.0]
        fx, fy, cx, cy = (float(_pick(rng, vals)) for _ in range(4))
        W, H = int(_pick(rng, [0, -1, 1, 3, 40])), int(_pick(rng, [0, -1, 1, 3, 30]))
        desc = f"fx={fx},fy={fy},cx={cx},cy={cy},{W}x{H}"

        def make() -> Any:
            s = PinholeModel(fx, fy, cx, cy, W, H)
            return Scan(range=np.full((H, W), 1.5, np.float32), sensor=s)
    else:
        T, desc = _adv_array(rng, 3)
        _save(d, "table", T)

        def make() -> Any:
            s = RayTableModel(T)
            return Scan(range=np.full(s.shape, 1.5, np.float32), sensor=s)

    def build() -> None:
        scan = make()
        _ = (scan.points, scan.seed, scan.valid, scan.up)
        if isinstance(scan.sensor, RayTableModel):
            _ = scan.sensor.pixel_angle
        _roundtrip(scan, d)

    return Job(f"{what}:{desc}", [(f"Scan({what})", build)])


def _save(d: Path, name: str, a: np.ndarray) -> None:
    """Keep an in-memory input for reproduction (objects as their repr only)."""
    if a.dtype == object:
        (d / f"{name}.repr.txt").write_text(repr(a)[:100_000])
    else:
        np.save(d / f"{name}.npy", a, allow_pickle=False)


def _degenerate_range(rng: np.random.Generator, H: int, W: int, f: float
                      ) -> tuple[np.ndarray, str]:
    """A degenerate range image of (H, W) for a pinhole of focal length ``f``."""
    from boxloc.scan import PinholeModel

    rays = PinholeModel(f, f, (W - 1) / 2, (H - 1) / 2, W, H).rays()
    kind = str(_pick(rng, ["one-valid", "all-equal", "plane", "tilted-plane", "noise",
                           "step", "checker-nan", "tiny-scale", "huge-scale", "subnormal",
                           "row", "column", "all-nan", "box", "two-valid"]))
    z = np.full((H, W), np.nan)
    if kind == "one-valid":
        z[int(rng.integers(0, H)), int(rng.integers(0, W))] = 1.5
        r = z
    elif kind == "two-valid":
        z.flat[rng.choice(H * W, size=min(2, H * W), replace=False)] = 1.5
        r = z
    elif kind == "all-equal":
        r = np.full((H, W), 1.5)
    elif kind in ("plane", "tilted-plane", "step", "box", "checker-nan"):
        n = np.array([0.0, 0.0, -1.0]) if kind != "tilted-plane" else np.array(
            [0.2, -0.3, -1.0])
        n /= np.linalg.norm(n)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = (n @ np.array([0.0, 0.0, 1.5])) / (rays @ n)
        if kind == "step":
            r[:, : W // 2] *= 0.9
        if kind == "box":
            r[H // 4: 3 * H // 4 + 1, W // 4: 3 * W // 4 + 1] *= 0.85
        if kind == "checker-nan":
            r[(np.add.outer(np.arange(H), np.arange(W)) % 2) == 0] = np.nan
    elif kind == "noise":
        r = rng.uniform(0.5, 3.0, (H, W))
    elif kind == "tiny-scale":
        r = np.full((H, W), 1e-6) * (1 + 0.1 * rng.random((H, W)))
    elif kind == "huge-scale":
        r = np.full((H, W), 1e30) * (1 + 0.1 * rng.random((H, W)))
    elif kind == "subnormal":
        r = np.full((H, W), 1e-44)
    elif kind == "row":
        z[H // 2, :] = 1.5
        r = z
    elif kind == "column":
        z[:, W // 2] = 1.5
        r = z
    else:
        r = z
    with np.errstate(all="ignore"):
        return np.asarray(r, np.float64).astype(np.float32), kind


def _gen_pipeline(rng: np.random.Generator, corpus: dict[str, Any], d: Path) -> Job:
    from boxloc.config import Config
    from boxloc.scan import PinholeModel, Scan

    H = int(_pick(rng, [1, 2, 3, 8, 24, 48]))
    W = int(_pick(rng, [1, 2, 5, 16, 32, 64]))
    f = float(_pick(rng, [0.8 * W + 1, 0.8 * W + 1, 1e-3, 1e6]))
    r, kind = _degenerate_range(rng, H, W, f)
    _save(d, "range", r)
    cfg = Config() if rng.random() < 0.6 else Config(
        alpha=float(_pick(rng, [1e-9, 0.001, 0.2, 0.49])),
        min_edge=float(_pick(rng, [0.001, 0.1, 0.5])), max_edge=float(_pick(rng, [1.0, 50.0])),
        direction_granularity=int(_pick(rng, [2, 4])))

    def run() -> None:
        from boxloc.pipeline import find_graspable_surfaces
        from boxloc.products import STAGES, products_equal
        from recorder.mcap.log import open_log
        from recorder.mcap.sink import McapRecorder

        scan = Scan(range=r, sensor=PinholeModel(f, f, (W - 1) / 2, (H - 1) / 2, W, H),
                    index=3, capture_time_ns=1_700_000_000_000_000_000)
        p = d / "run.mcap"
        with McapRecorder(p, config=cfg, fsync=False, max_points=200, session="fuzz") as rec:
            res = find_graspable_surfaces(scan, cfg, observer=rec)
        (back,) = list(open_log(p).scans())
        diff = [s for s in STAGES if products_equal(getattr(res, s), back.products[s])]
        if diff or back.scan.range.tobytes() != scan.range.tobytes():
            raise AssertionError(f"the recorded result differs from the run: {diff}")

    return Job(f"{kind}-{H}x{W}-f{f:g}", [("find_graspable_surfaces", run)])


def bag_steps(path: Path, d: Path) -> list[Step]:
    """Read every frame of a bag; record each and read it back bit for bit."""

    def read() -> None:
        from boxloc.io.rosbag import open_bag

        for scan in open_bag(path, max_pixels=1 << 20):
            _ = (scan.points, scan.seed, scan.up)
            _roundtrip(scan, d)

    return [("read_bag", read)]


_HOSTILE_IMAGE = ("size", "step", "short", "encoding", "bigendian", "storm")
_HOSTILE_INFO = ("nan-k", "zero-k", "distortion", "roi", "binning", "info-size")
_HOSTILE_OTHER = ("cloud-flat", "cloud-fields", "cloud-short", "tf-cycle", "tf-zero-quat",
                  "tf-nan", "stamp-zero")


def _hostile_bag(rng: np.random.Generator, p: Path) -> str:
    """A valid bag (written by rosbags) whose messages disagree with themselves."""
    from boxloc.io.rosbag import (
        BagWriter,
        camera_info_message,
        cloud_message,
        image_message,
        tf_message,
    )
    from boxloc.scan import PinholeModel

    H, W = int(_pick(rng, [1, 2, 7, 36])), int(_pick(rng, [1, 3, 48]))
    sensor = PinholeModel(39.4, 39.4, (W - 1) / 2, (H - 1) / 2, W, H)
    what = str(_pick(rng, _HOSTILE_IMAGE + _HOSTILE_INFO + _HOSTILE_OTHER))
    t = 1_700_000_000_000_000_000
    z, _ = _storm(rng, (H, W), np.float64)
    with np.errstate(all="ignore"):
        depth = (np.clip(np.nan_to_num(z * 1000, nan=0), 0, 65535).astype(np.uint16)
                 if rng.random() < 0.5 else z.astype(np.float32))
    with BagWriter(p, storage="mcap" if p.suffix == ".mcap" else "sqlite3",
                   single_file=True) as w:
        T = w.types
        info = camera_info_message(T, sensor, t, "cam")
        img = image_message(T, depth, t, "cam")
        if what == "size":
            img.height, img.width = int(_pick(rng, [0, 2**31 - 1, 2**32 - 1, 70000])), W
        elif what == "step":
            img.step = int(_pick(rng, [0, 1, 2**32 - 1]))
        elif what == "short":
            img.data = img.data[: int(rng.integers(0, max(1, img.data.size)))]
        elif what == "encoding":
            img.encoding = str(_pick(rng, ["", "rgb8", "16SC1", "64FC1", "\x00", "mono16"]))
        elif what == "bigendian":
            img.is_bigendian = 1
        elif what == "nan-k":
            info.k = np.full(9, np.nan)
        elif what == "zero-k":
            info.k = np.zeros(9)
        elif what == "distortion":
            info.distortion_model = str(_pick(rng, ["plumb_bob", "equidistant", "", "x"]))
            info.d = rng.normal(0, float(_pick(rng, [0.01, 1.0, 1e6])),
                                int(_pick(rng, [0, 1, 4, 5, 8, 14])))
        elif what == "roi":
            info.roi.x_offset, info.roi.width = int(rng.integers(0, 2**31)), W
        elif what == "binning":
            info.binning_x = int(_pick(rng, [2, 2**31 - 1]))
        elif what == "info-size":
            info.width = W + 1
        if what.startswith("cloud"):
            P = rng.normal(0, 1, (H, W, 3)).astype(np.float32)
            c = cloud_message(T, P.reshape(1, -1, 3) if what == "cloud-flat" else P, t, "cam")
            if what == "cloud-fields":
                c.fields[int(rng.integers(0, 3))].datatype = int(_pick(rng, [1, 2, 7, 8, 99]))
                c.fields[0].offset = int(_pick(rng, [0, 11, 2**31]))
            elif what == "cloud-short":
                c.point_step = int(_pick(rng, [0, 4, 12]))
                c.data = c.data[: int(rng.integers(0, max(1, c.data.size)))]
            w.write("/cam/points", c, t)
        else:
            w.write("/cam/camera_info", info, t)
            if what == "stamp-zero":
                img.header.stamp.sec, img.header.stamp.nanosec = 0, 0
            w.write("/cam/image_raw", img, t)
        if what.startswith("tf"):
            M = np.eye(4)
            tf = tf_message(T, "base", "cam", M, t)
            q = tf.transforms[0].transform.rotation
            if what == "tf-zero-quat":
                q.x = q.y = q.z = q.w = 0.0
            elif what == "tf-nan":
                tf.transforms[0].transform.translation.x = float("nan")
            w.write("/tf_static", tf, t)
            if what == "tf-cycle":
                w.write("/tf_static", tf_message(T, "cam", "base", M, t), t)
    return what


def _gen_bag(rng: np.random.Generator, corpus: dict[str, Any], d: Path) -> Job:
    if rng.random() < 0.6:
        src = Path(str(_pick(rng, corpus["bags"])))
        data, op = mutate_bytes(rng, src.read_bytes())
        p = d / f"fuzzed{src.suffix}"
        p.write_bytes(data)
        return Job(f"bag-mutate-{op}", bag_steps(p, d))
    p = d / f"fuzzed{_pick(rng, ['.mcap', '.db3'])}"
    what = _hostile_bag(rng, p)
    return Job(f"bag-hostile-{what}", bag_steps(p, d))


_GENERATORS: dict[str, Callable[[np.random.Generator, dict[str, Any], Path], Job]] = {
    "log-bytes": _gen_log_bytes, "log-records": _gen_log_records, "npz": _gen_npz,
    "image": _gen_image, "cloud": _gen_cloud, "scan": _gen_scan, "pipeline": _gen_pipeline,
    "bag": _gen_bag,
}


def generate(case: Case, corpus: dict[str, Any], d: Path) -> Job:
    """Write the case's input files into ``d`` and return its steps (nothing is run)."""
    d.mkdir(parents=True, exist_ok=True)
    return _GENERATORS[case.category](case.rng(), corpus, d)


# --- running one case ------------------------------------------------------------------------


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


# --- worker processes ------------------------------------------------------------------------


def _warm_up(corpus: dict[str, Any], tmp: Path) -> None:
    """Import and JIT-compile everything once, so that per-case memory and time are the
    case's own."""
    import cv2  # noqa: F401
    import open3d  # noqa: F401

    from boxloc.io import read_scan
    from recorder.commands import log_info

    for i, cat in enumerate(CATEGORIES):
        case = Case(-1 - i, cat, 0)
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


# --- the run ---------------------------------------------------------------------------------


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


# --- the bench section and the command line --------------------------------------------------


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

    ap = argparse.ArgumentParser(prog="python -m recorder.fuzz", description=__doc__.split(
        "\n")[0])
    ap.add_argument("--n", type=int, default=200, help="number of cases")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="work directory (kept)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--case", default=None, help="re-run a saved failing case directory")
    a = ap.parse_args(argv)
    if a.case:
        print(json.dumps(reproduce(a.case), indent=1))
        return 0
    rep = run_fuzz(a.n, a.seed, workdir=a.out, workers=a.workers, progress=True)
    print(json.dumps({k: v for k, v in rep.items() if k != "failures"}, indent=1))
    for f in rep["failures"]:
        print(f"FAILURE case {f['case']} {f['category']} {f['kind']} [{f['step']}] "
              f"{f['what']}: {f['detail']}")
    return 1 if rep["outcomes"]["failure"] else 0


if __name__ == "__main__":
    sys.exit(main())

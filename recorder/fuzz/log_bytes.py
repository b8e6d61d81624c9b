"""The ``log-bytes`` cases: a log with its bytes mutated, opened strictly and with
``allow_truncated``, recovered, read back and summarized.
"""

from __future__ import annotations

import contextlib
import io
import json
import struct
from pathlib import Path
from typing import Any

import numpy as np

from recorder.fuzz.cases import Job, Step
from recorder.fuzz.mutate import _mutate_chunk_content, _mutate_record_frame, mutate_bytes


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

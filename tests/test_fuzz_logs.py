"""Property tests of the log reader and of recovery on damaged logs (hypothesis): any cut,
any byte damage, any spliced or structurally hostile log ends in a read, a recovery or a
LogError with a one-line message; a truncated log keeps, bit for bit, every scan whose
chunk ended before the cut; a decoded array never exceeds its declared shape or the limit.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from factories import feed, make_result, make_scan
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from boxloc.errors import BoxlocError, LogError
from boxloc.products import STAGES, products_equal
from recorder.annotate import read_sidecar, sidecar_path
from recorder.fuzz import _mutate_chunk_content, _mutate_record_frame, log_steps, run_step
from recorder.mcap import encode as E
from recorder.mcap.log import open_log
from recorder.mcap.proto import message_class
from recorder.mcap.recover import recover_log
from recorder.mcap.sink import McapRecorder

CI = settings(max_examples=100, deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow,
                                     HealthCheck.function_scoped_fixture])
N_SCANS = 4


class SmallLog(tuple):  # type: ignore[type-arg]
    """(path, results, chunk ends), with a short repr for hypothesis' reports."""

    def __repr__(self) -> str:
        return f"SmallLog({self[0].name})"


@pytest.fixture(scope="module")
def log(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, ...]:
    """A small log of four scans (one with a ray table), and the byte offset at which each
    scan's chunk (one per scan) ends."""
    path = tmp_path_factory.mktemp("logs") / "small.mcap"
    scans = [make_scan(i, shape=(24, 32), raytable=(i == 2)) for i in range(N_SCANS)]
    results = [make_result(s, i) for i, s in enumerate(scans)]
    with McapRecorder(path, fsync=False) as rec:
        for s, r in zip(scans, results):
            feed(rec, s, r)
    summary = open_log(path).summary
    assert summary is not None
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) == N_SCANS
    ends = [c.chunk_start_offset + c.chunk_length for c in chunks]
    (_, header_length), = [struct.unpack_from("<BQ", path.read_bytes(), 8)]
    return SmallLog((path, results, ends, 8 + 9 + header_length))


def _outcome_is_clean(path: Path, d: Path) -> None:
    for name, fn in log_steps(path, d):
        status, what, detail, tb = run_step(fn)
        assert status != "failure", f"{name}: {what}: {detail}\n{tb}"


@CI
@given(cut=st.integers(0, 10**9))
def test_any_truncation_keeps_every_whole_scan(tmp_path: Path, cut: int,
                                               log: tuple[Any, ...]) -> None:
    src, results, ends, header_end = log
    data = src.read_bytes()
    cut %= len(data) + 1
    p = tmp_path / "cut.mcap"
    p.write_bytes(data[:cut])
    whole = [i for i, e in enumerate(ends) if e <= cut]
    if cut < len(data):
        with pytest.raises(LogError) as info:
            list(open_log(p).scans())
        assert "\n" not in str(info.value)
    if cut < 8:
        with pytest.raises(LogError):
            recover_log(p, tmp_path / "rec.mcap", overwrite=True)
        return
    if cut < header_end:  # not even the header: nothing to read, an empty recovery
        with pytest.raises(LogError, match="header"):
            open_log(p, allow_truncated=True)
        assert recover_log(p, tmp_path / "rec.mcap", overwrite=True).scan_indices == []
        return
    # In place, without a summary: every whole scan, then perhaps the one cut short.
    got = list(open_log(p, allow_truncated=True).scans())
    done = [r for r in got if r.complete]
    assert [r.index for r in done] == whole
    assert all(r.error is not None for r in got if not r.complete)
    report = recover_log(p, tmp_path / "rec.mcap", overwrite=True)
    assert report.scan_indices == whole
    for rec in open_log(report.output).scans():
        want = results[rec.index]
        for s in STAGES:
            assert products_equal(getattr(want, s), rec.products[s]) == []


@CI
@given(edits=st.lists(st.tuples(st.integers(0, 10**9), st.integers(0, 255)), min_size=1,
                      max_size=12))
def test_any_byte_damage_is_read_recovered_or_refused(tmp_path: Path, edits: list[Any],
                                                      log: tuple[Any, ...]
                                                      ) -> None:
    src = log[0]
    data = bytearray(src.read_bytes())
    for pos, byte in edits:
        data[pos % len(data)] = byte
    p = tmp_path / "bad.mcap"
    p.write_bytes(bytes(data))
    _outcome_is_clean(p, tmp_path)


@CI
@given(seed=st.integers(0, 2**32 - 1), inner=st.booleans())
def test_damage_behind_a_valid_crc_or_in_the_framing(tmp_path: Path, seed: int, inner: bool,
                                                     log: tuple[Any, ...]
                                                     ) -> None:
    """Records inside a chunk whose CRC was fixed up, and record lengths and opcodes."""
    src = log[0]
    rng = np.random.default_rng(seed)
    mutate = _mutate_chunk_content if inner else _mutate_record_frame
    data, _ = mutate(rng, src.read_bytes())
    p = tmp_path / "bad.mcap"
    p.write_bytes(data)
    _outcome_is_clean(p, tmp_path)


@CI
@given(a=st.integers(0, 10**9), b=st.integers(0, 10**9))
def test_two_logs_spliced(tmp_path: Path, a: int, b: int,
                          log: tuple[Any, ...]) -> None:
    src = log[0]
    data = src.read_bytes()
    p = tmp_path / "spliced.mcap"
    p.write_bytes(data[: a % len(data)] + data[b % len(data):])
    _outcome_is_clean(p, tmp_path)


DTYPE_TEXT = st.one_of(st.sampled_from(["<f4", "<f8", ">f8", "|b1", "<i8", "<u2", "|u1", "<U3",
                                        "|U0", "<U999999", "|O", "<c16", "<f2", "<M8[ns]",
                                        "|V8"]),
                       st.text(max_size=8))


@settings(max_examples=300, deadline=None, derandomize=True, database=None)
@given(name=st.text(max_size=20), dtype=DTYPE_TEXT,
       shape=st.lists(st.one_of(st.integers(0, 8), st.integers(0, 2**64 - 1)), max_size=10),
       data=st.binary(max_size=80), filt=st.integers(0, 6))
def test_a_decoded_array_is_bounded_by_its_shape_and_the_limit(name: str, dtype: str,
                                                               shape: list[int], data: bytes,
                                                               filt: int) -> None:
    msg = message_class("Array")()
    msg.name, msg.dtype, msg.data, msg.filter = name, dtype, data, filt
    msg.shape.extend(shape)
    limits = E.DecodeLimits(max_array_bytes=1 << 20)
    try:
        a = E.msg_to_array(msg, limits)
    except LogError as e:
        assert "\n" not in str(e)
        return
    assert a.shape == tuple(shape)
    assert a.dtype == np.dtype(dtype) and a.dtype.kind not in "OVcM"
    assert a.nbytes <= limits.max_array_bytes


DECODERS = {
    "range": E.decode_range, "sensor": E.decode_sensor, "scan_info": E.decode_scan_info,
    "result": E.decode_result_info, "tests": E.decode_test_columns, "timing": E.decode_timing,
    "error": E.decode_error, "outcome": E.decode_outcome, "labels": E.decode_labels,
    "scan_end": E.decode_scan_end, "locate": E.decode_locate_json,
    **{s: (lambda data, s=s: E.decode_product(s, data, E.empty_test_columns()))
       for s in STAGES},
}


@settings(max_examples=300, deadline=None, derandomize=True, database=None)
@given(which=st.sampled_from(sorted(DECODERS)), data=st.binary(max_size=300))
def test_every_decoder_on_garbage(which: str, data: bytes) -> None:
    try:
        DECODERS[which](data)
    except LogError as e:
        assert "\n" not in str(e)


@CI
@given(lines=st.lists(st.one_of(st.text(max_size=60), st.sampled_from([
    '{"v": 1, "scan": 0, "surface": 0, "ok": true}', '{"v": 2}', "[" * 5000 + "]" * 5000,
    '{"v": 1, "scan": "0", "surface": 0, "ok": true}', "null"])), max_size=6))
def test_a_sidecar_of_any_lines(tmp_path: Path, lines: list[str]) -> None:
    p = tmp_path / "x.mcap"
    sidecar_path(p).write_bytes(("\n".join(lines) + "\n").encode("utf-8", "surrogatepass"))
    try:
        out = read_sidecar(p)
    except BoxlocError as e:
        assert "\n" not in str(e)
        return
    assert all(isinstance(o.ok, bool) for o in out)


def test_range_records_are_fuzzed_in_their_own_format() -> None:
    """A schema-1.4 ``/scan/range`` (a ScanRange record) is mutated as a record, field by
    field, not as a Foxglove RawImage; the same seed gives the same bytes."""
    from recorder.fuzz.log_records import _mutate_image

    data = E.encode_range(make_scan(), 0)
    assert E.is_range_record(data)
    kinds = set()
    for seed in range(40):
        out, kind = _mutate_image(np.random.default_rng(seed), data)
        again, _ = _mutate_image(np.random.default_rng(seed), data)
        assert out == again
        assert kind.startswith("range-"), kind
        kinds.add(kind)
    assert len(kinds) >= 4, kinds   # several fields were mutated, not just the bytes

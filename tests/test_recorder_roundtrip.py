"""Products and scans go through the MCAP log and come back bit for bit."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from factories import feed, make_result, make_scan

from boxloc.config import Config
from boxloc.errors import LogError
from boxloc.products import STAGES, products_equal
from boxloc.stats import TestKind
from recorder.mcap import channels as C
from recorder.mcap import encode as E
from recorder.mcap.log import open_log
from recorder.mcap.proto import message_class
from recorder.mcap.sink import McapRecorder


def _same_scan(a, b) -> None:
    assert a.range.dtype == b.range.dtype == np.float32
    assert a.range.tobytes() == b.range.tobytes()
    assert type(a.sensor) is type(b.sensor)
    assert a.sensor.rays().tobytes() == b.sensor.rays().tobytes()
    assert a.sensor.to_dict() == b.sensor.to_dict()
    if a.sensor_to_base is None:
        assert b.sensor_to_base is None
    else:
        assert a.sensor_to_base.tobytes() == b.sensor_to_base.tobytes()
    assert (a.capture_time_ns, a.index, a.source, a.meta) == (
        b.capture_time_ns, b.index, b.source, b.meta)
    assert a.seed == b.seed


# --- products through the encoder ---------------------------------------------------------


def _test_columns(stage: str, product):  # type: ignore[no-untyped-def]
    """The product's tests through /boxloc/tests rows, as the reader gets them."""
    if not hasattr(product, "tests"):
        return None
    tests = E.decode_test_columns(E.encode_test_rows(0, {stage: product.tests}))
    return tests.get(stage, E.empty_test_columns())


def _round_trip(stage: str, product):  # type: ignore[no-untyped-def]
    """Encode a product and its tests as the recorder does, decode as the reader does."""
    return E.decode_product(stage, E.encode_product(stage, product, 0, 0),
                            _test_columns(stage, product))


@pytest.mark.parametrize("empty", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("stage", STAGES)
def test_every_product_round_trips_bit_for_bit(stage: str, seed: int, empty: bool) -> None:
    scan = make_scan(seed)
    product = getattr(make_result(scan, seed, empty=empty), stage)
    back = _round_trip(stage, product)
    assert type(back) is type(product)
    assert products_equal(product, back) == []


def test_tests_are_recorded_once_as_rows() -> None:
    r = make_result(make_scan(0), 0)
    data = E.encode_product("hypotheses", r.hypotheses, 0, 0)
    _, arrays = E.decode_arrays(data, "HypothesisSet")
    assert "tests/statistic" not in arrays and "tests/alpha" in arrays
    with pytest.raises(LogError, match="tests/rows are missing|/boxloc/tests"):
        E.decode_product("hypotheses", data)
    rows = E.decode_test_rows(E.encode_test_rows(0, {"hypotheses": r.hypotheses.tests}))
    t = r.hypotheses.tests
    assert len(rows) == len(t)
    assert rows[0] == {"stage": "hypotheses", "kind": TestKind(int(t.kind[0])).name,
                       "a": int(t.a[0]), "b": int(t.b[0]), "statistic": float(t.statistic[0]),
                       "dof": float(t.dof[0]), "critical": float(t.critical[0]),
                       "p_value": float(t.p_value[0]), "alpha": t.alpha,
                       "accepted": bool(t.accepted[0])}


def test_test_columns_of_other_dtypes_stay_in_the_product() -> None:
    r = make_result(make_scan(0), 0)
    t = r.lines.tests
    wide = dataclasses.replace(t, a=t.a.astype(np.int64) + 2**40)
    lines = dataclasses.replace(r.lines, tests=wide)
    _, arrays = E.decode_arrays(E.encode_product("lines", lines, 0, 0), "LineSet")
    assert arrays["tests/a"].dtype == np.int64
    assert products_equal(_round_trip("lines", lines), lines) == []


def test_decision_tests_keep_nan_p_values() -> None:
    # Decisions that are not chi-square tests record p = NaN; it must survive as NaN.
    r = make_result(make_scan(0), 0)
    t = r.vertices.tests
    assert np.isnan(t.p_value).any()
    back = _round_trip("vertices", r.vertices)
    assert np.isnan(back.tests.p_value).sum() == np.isnan(t.p_value).sum()


_WRAP = (np.arange(2**31 - 60, 2**31 + 60, dtype=np.int64) % 2**32).astype(np.uint32).view(
    np.int32)  # increasing modulo 2**32: crosses from int32 max to int32 min


@pytest.mark.parametrize("a,filt", [
    (np.arange(1000, dtype=np.int32) * 3 + 7, 2),                       # delta
    (_WRAP, 2),                                                          # delta wraps around
    (np.arange(500, dtype=np.uint64)[::-1].copy(), 2),
    (np.random.default_rng(1).integers(-9, 9, 300).astype(np.int16), 1),  # no delta
    (np.random.default_rng(0).normal(size=(40, 6, 6)), 1),              # not symmetric
    (np.random.default_rng(1).integers(0, 255, 300).astype(np.uint8), 0),
    (np.array([np.nan, -0.0, np.inf, 1e-300] * 20), 1),
    (np.zeros((0, 3)), 0),
    (np.asarray(3.5), 0),
    (np.asarray("héllo"), 0),
    (np.ones((30, 4), dtype=">f4"), 1),
    (np.array([True, False] * 50), 0),
])
def test_arrays_round_trip_through_every_filter(a: np.ndarray, filt: int) -> None:
    msg = message_class("Array")()
    E.array_to_msg(msg, "x", a)
    assert msg.filter == filt
    back = E.msg_to_array(msg)
    assert back.dtype == a.dtype and back.shape == a.shape
    assert back.tobytes() == np.ascontiguousarray(a).tobytes()


def test_symmetric_matrices_are_stored_once_and_exactly() -> None:
    rng = np.random.default_rng(3)
    A = rng.normal(size=(50, 9, 9))
    S = A @ np.swapaxes(A, 1, 2)
    S = (S + np.swapaxes(S, 1, 2)) / 2  # bitwise symmetric
    msg = message_class("Array")()
    E.array_to_msg(msg, "cov", S)
    assert msg.filter == 3 and len(msg.data) == 50 * 45 * 8
    assert E.msg_to_array(msg).tobytes() == S.tobytes()


# --- untrusted input ------------------------------------------------------------------------


def _array_msg(**kw):  # type: ignore[no-untyped-def]
    msg = message_class("Array")()
    for k, v in kw.items():
        if k == "shape":
            msg.shape.extend(v)
        else:
            setattr(msg, k, v)
    return msg


@pytest.mark.parametrize("msg,match", [
    (_array_msg(name="x", dtype="|O", shape=[1], data=b"\0" * 8), "dtype"),
    (_array_msg(name="x", dtype="<f8", shape=[3], data=b"\0" * 8), "bytes"),
    (_array_msg(name="x", dtype="<f8", shape=[1 << 40, 1 << 20], data=b""), "limit"),
    (_array_msg(name="x", dtype="<f8", shape=[1] * 20, data=b"\0" * 8), "dimensions"),
    (_array_msg(name="x", dtype="|u1", shape=[8], data=b"\0" * 8, filter=1), "not valid"),
    (_array_msg(name="x", dtype="<f8", shape=[2, 3], data=b"\0" * 48, filter=3), "not valid"),
    (_array_msg(name="x", dtype="<f8", shape=[1], data=b"\0" * 8, filter=9), "filter"),
])
def test_bad_arrays_are_refused(msg, match: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(LogError, match=match):
        E.msg_to_array(msg)


def test_arrays_are_bounded_by_the_configured_limit() -> None:
    msg = message_class("Array")()
    E.array_to_msg(msg, "x", np.zeros(1000))
    with pytest.raises(LogError, match="limit"):
        E.msg_to_array(msg, E.DecodeLimits(max_array_bytes=4000))


def test_bad_array_names_are_refused() -> None:
    data = E.encode_arrays("EdgeMap", {"../../etc/passwd": np.zeros(2)}, 0, 0)
    with pytest.raises(LogError, match="bad array name"):
        E.decode_arrays(data, "EdgeMap")


def test_missing_fields_are_refused() -> None:
    data = E.encode_arrays("EdgeMap", {"labels": np.zeros((2, 2), np.uint8)}, 0, 0)
    with pytest.raises(LogError, match="lacks field"):
        E.decode_product("edges", data)


@pytest.mark.parametrize("stage", STAGES)
def test_a_record_without_the_fields_newer_than_its_log_reads_back(stage: str) -> None:
    # a log of an older minor version lacks the fields added since (those with a
    # default): it must still read, with the defaults filled in
    import dataclasses as dc
    product = getattr(make_result(make_scan(0), 0), stage)
    newer = [f.name for f in dc.fields(product) if f.default is not dc.MISSING]
    _, arrays = E.decode_arrays(E.encode_product(stage, product, 0, 0), E.PRODUCT_RECORDS[stage])
    old = {k: v for k, v in arrays.items() if k.split("/")[0] not in newer}
    back = E.decode_product(stage, E.encode_arrays(E.PRODUCT_RECORDS[stage], old, 0, 0),
                            _test_columns(stage, product))
    assert type(back) is type(product)
    fresh = type(product)(**{f.name: getattr(product, f.name) for f in dc.fields(product)
                             if f.name not in newer})
    assert products_equal(back, fresh) == []


def test_an_unknown_major_version_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    r = make_result(make_scan(0), 0)
    monkeypatch.setattr(E, "SCHEMA_VERSION", "2.0")
    newer = E.encode_product("selection", r.selection, 0, 0)
    monkeypatch.setattr(E, "SCHEMA_VERSION", "1.7")
    minor = E.encode_product("selection", r.selection, 0, 0)
    monkeypatch.undo()
    with pytest.raises(LogError, match="major version 2"):
        E.decode_product("selection", newer)
    # A newer minor version is compatible.
    assert products_equal(E.decode_product("selection", minor), r.selection) == []


def test_a_log_of_an_unknown_major_version_is_refused(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    scan = make_scan(0)
    monkeypatch.setattr(E, "SCHEMA_VERSION", "2.0")
    with McapRecorder(tmp_path / "v2.mcap") as rec:
        feed(rec, scan, make_result(scan, 0))
    monkeypatch.undo()
    log = open_log(tmp_path / "v2.mcap")
    with pytest.raises(LogError, match="major version 2"):
        list(log.scans())


# --- scans and results through a log --------------------------------------------------------


def test_scans_and_results_round_trip_through_a_log(tmp_path) -> None:  # type: ignore[no-untyped-def]
    scans = [make_scan(0), make_scan(1, raytable=True), make_scan(2, pose=False),
             make_scan(3, raytable=True, pose=False), make_scan(4)]
    results = [make_result(s, i, empty=(i == 2)) for i, s in enumerate(scans)]
    path = tmp_path / "rt.mcap"
    with McapRecorder(path) as rec:
        for s, r in zip(scans, results):
            feed(rec, s, r)
    log = open_log(path)
    records = list(log)
    assert [r.index for r in records] == [s.index for s in scans]
    for s, r, rec in zip(scans, results, records):
        _same_scan(s, rec.scan)
        assert rec.complete and rec.error is None
        assert products_equal(r, rec.result) == []
        assert rec.timing_ms == r.timing_ms  # recorded, though never compared
        assert rec.log_time_ns == s.capture_time_ns
        # A Scan computed from the log gives the same points, bit for bit.
        assert rec.scan.points.tobytes() == s.points.tobytes()


def test_scans_without_capture_time_get_distinct_increasing_log_times(tmp_path) -> None:  # type: ignore[no-untyped-def]
    scans = [make_scan(i, capture_time_ns=0, index=i) for i in range(3)]
    with McapRecorder(tmp_path / "t0.mcap") as rec:
        for s in scans:
            feed(rec, s, make_result(s, 0))
    times = [r.log_time_ns for r in open_log(tmp_path / "t0.mcap")]
    assert times == [C.scan_log_time(0, i) for i in range(3)]
    assert times == sorted(set(times))


def test_sequence_is_the_scan_index_and_log_time_the_capture_time(tmp_path) -> None:  # type: ignore[no-untyped-def]
    scan = make_scan(7, index=42)
    with McapRecorder(tmp_path / "seq.mcap") as rec:
        feed(rec, scan, make_result(scan, 0))
    msgs = list(open_log(tmp_path / "seq.mcap").messages())
    assert {m.sequence for m in msgs} == {42}
    assert {m.log_time for m in msgs} == {scan.capture_time_ns}
    assert {m.publish_time for m in msgs} == {scan.capture_time_ns}


def test_a_failed_scan_is_recorded_with_its_error(tmp_path) -> None:  # type: ignore[no-untyped-def]
    scan = make_scan(0)
    r = make_result(scan, 0)
    with McapRecorder(tmp_path / "err.mcap") as rec:
        rec.on_scan(scan, Config())
        rec.on_edges(scan, r.edges)
        rec.on_error(scan, RuntimeError("lines exploded\nsecond line"))
        # The next scan still records normally.
        s2 = make_scan(1)
        feed(rec, s2, make_result(s2, 1))
    records = list(open_log(tmp_path / "err.mcap"))
    assert records[0].error == {"scan_index": 0, "stage": "lines", "error_type": "RuntimeError",
                                "message": "lines exploded"}
    assert set(records[0].products) == {"edges"} and records[0].result is None
    _same_scan(scan, records[0].scan)
    assert records[1].complete


def test_finish_is_idempotent_and_closes_an_unfinished_scan(tmp_path) -> None:  # type: ignore[no-untyped-def]
    scan = make_scan(0)
    rec = McapRecorder(tmp_path / "fin.mcap")
    rec.on_scan(scan, Config())
    rec.finish()
    rec.finish()
    (only,) = list(open_log(tmp_path / "fin.mcap"))
    assert only.error is not None and only.error["error_type"] == "Interrupted"


def test_an_existing_log_is_never_overwritten(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from boxloc.errors import InputError

    p = tmp_path / "x.mcap"
    p.write_bytes(b"precious")
    with pytest.raises(InputError, match="refusing to overwrite"):
        McapRecorder(p)
    assert p.read_bytes() == b"precious"


def test_one_topic_has_one_schema(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from recorder.mcap.sink import McapFile

    f = McapFile(tmp_path / "s.mcap", open(tmp_path / "s.mcap", "wb"), library="t")
    f.spec_channel(C.SCAN_RANGE)
    with pytest.raises(ValueError, match="cannot write"):
        f.channel(C.SCAN_RANGE, schema_name="other", schema_encoding="protobuf",
                  schema_data=b"", message_encoding="protobuf")
    f.finish()


def test_an_exception_in_the_with_block_ends_the_scan_with_it(tmp_path) -> None:  # type: ignore[no-untyped-def]
    scan = make_scan(0)
    with pytest.raises(ZeroDivisionError), McapRecorder(tmp_path / "x.mcap") as rec:
        rec.on_scan(scan, Config())
        rec.on_edges(scan, make_result(scan, 0).edges)
        1 / 0  # noqa: B018
    (only,) = list(open_log(tmp_path / "x.mcap"))
    assert only.error["error_type"] == "ZeroDivisionError" and only.error["stage"] == "lines"

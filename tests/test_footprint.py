"""Footprint of a log: the range image's lossless image filters (4: schema 1.4 and 1.5,
still read; 5: schema 1.6), the range preview, the views' point grid, and old logs (a
RawImage range, schema <= 1.3) still read; a 1.6 log rewritten for 1.4 / 1.5 readers.

Sizes here are deterministic byte counts of fixed scans, never times.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import zstandard
from factories import feed, make_result, make_scan
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap.reader import make_reader

from boxloc.errors import LogError
from boxloc.scan import Scan
from boxloc.stats import float32_precision
from recorder.mcap import channels as C
from recorder.mcap import encode as E
from recorder.mcap.log import open_log
from recorder.mcap.proto import message_class
from recorder.mcap.sink import ZSTD_LEVEL, McapRecorder

ROOT = Path(__file__).resolve().parents[1]

#: bit patterns a range can hold: NaNs with payloads, both zeros, infinities, denormals
SPECIAL_F4 = np.array([0x7FC00000, 0x7FC00001, 0xFFC12345, 0x7F800001, 0x00000000,
                       0x80000000, 0x7F800000, 0xFF800000, 0x00000001, 0x007FFFFF,
                       0x3F800000, 0x3F800001], np.uint32)


def _array_msg() -> object:
    return message_class("Product")().arrays.add()


def _roundtrip(a: np.ndarray, image_filter: int = 5) -> np.ndarray:
    m = _array_msg()
    E.array_to_msg(m, "x", a, image=True, image_filter=image_filter)
    assert m.filter == image_filter  # type: ignore[attr-defined]
    b = E.msg_to_array(m)
    assert b.dtype == a.dtype and b.shape == a.shape and b.tobytes() == a.tobytes()
    return b


@pytest.mark.parametrize("image_filter", [4, 5])
@pytest.mark.parametrize("dtype", ["<f4", "<f8", "<u2", "<i4", "<i8", ">f4"])
@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (9, 1), (37, 53)])
def test_the_image_filters_keep_every_bit(image_filter: int, dtype: str,
                                          shape: tuple[int, int]) -> None:
    """Random bytes: every bit pattern (NaNs with payloads among the floats)."""
    rng = np.random.default_rng([image_filter, len(dtype), ord(dtype[0]), ord(dtype[-1]),
                                 *shape])
    dt = np.dtype(dtype)
    raw = rng.integers(0, 256, size=(*shape, dt.itemsize), dtype=np.uint8).tobytes()
    _roundtrip(np.frombuffer(raw, dt).reshape(shape), image_filter)


def _noisy_surface(dtype: str, shape: tuple[int, int], sigma: float,
                   seed: int) -> np.ndarray:
    """A tilted plane at 1.5-2.5 (of the dtype's units) with Gaussian noise."""
    rng = np.random.default_rng(seed)
    H, W = shape
    v = 1.5 + np.linspace(0, 1, W)[None, :] * 0.7 + np.linspace(0, 1, H)[:, None] * 0.3
    v = v + rng.normal(0, sigma, shape)
    dt = np.dtype(dtype)
    if dt.kind in "iu":
        v = v * 1000  # millimetres
    return v.astype(dt)


@pytest.mark.parametrize("dtype", ["<f4", "<f8", ">f4", "<u2", "<i8"])
@pytest.mark.parametrize("sigma", [0.0, 1e-4, 3e-3, 0.3])
def test_filter_5_keeps_noisy_images_with_no_returns(dtype: str, sigma: float) -> None:
    """The split point follows the noise (k from 8 to 16); no-return runs at the start, at
    a row's end and start, whole rows and single pixels; escapes where the noise is huge."""
    a = _noisy_surface(dtype, (48, 64), sigma, seed=int(sigma * 1e4) + len(dtype))
    if a.dtype.kind == "f":
        a = a.copy()
        a[0, :5] = np.nan
        a[3, 60:] = np.nan
        a[4, :2] = np.nan
        a[10:12, :] = np.nan
        a[20, ::7] = np.nan
        bits = a.view(a.dtype.str.replace("f", "u"))  # NaNs with payloads, negative NaN
        bits[31, 7] = 0x7FC00001 if a.dtype.itemsize == 4 else 0x7FF8000000000001
        bits[32, 8] = 0xFFC12345 if a.dtype.itemsize == 4 else 0xFFF8000000012345
        assert np.isnan(a[31, 7]) and np.isnan(a[32, 8])
    _roundtrip(a)
    _roundtrip(np.ascontiguousarray(a[:, :1]))  # one column: every pixel predicted from above


def test_filter_5_keeps_images_of_no_return_only_and_of_one_value() -> None:
    _roundtrip(np.full((5, 7), np.nan, "<f4"))
    _roundtrip(np.full((5, 7), -0.0, "<f8"))
    _roundtrip(np.full((3, 4), np.iinfo(np.int64).min, "<i8"))
    a = np.zeros((6, 6), "<f4")
    a[::2, 1::2] = np.inf
    a[1::2, ::2] = -np.inf
    _roundtrip(a)


def test_filter_5_splits_where_the_noise_ends() -> None:
    """k grows with the noise: each part is about as large as the information in it."""
    ks = []
    for sigma in (1e-5, 1e-4, 1e-3):
        a = _noisy_surface("<f4", (120, 160), sigma, seed=3)
        m = _array_msg()
        E.array_to_msg(m, "x", a, image=True)
        ks.append(m.data[0])  # type: ignore[attr-defined]
    assert ks == sorted(ks) and ks[0] < ks[-1] and all(8 <= k <= 16 for k in ks), ks


def _split_msg(a: np.ndarray) -> object:
    m = _array_msg()
    E.array_to_msg(m, "x", a, image=True)
    return m


def _set_header(data: bytes, **fields: int) -> bytes:
    k, flags, n_esc, n_nan, *lengths = E._IMAGE_HEADER.unpack_from(data)
    vals = {"k": k, "flags": flags, "n_esc": n_esc, "n_nan": n_nan}
    vals.update(fields)
    return E._IMAGE_HEADER.pack(vals["k"], vals["flags"], vals["n_esc"], vals["n_nan"],
                                *lengths) + data[E._IMAGE_HEADER.size:]


@pytest.mark.parametrize("bad, match", [
    ("short", "shorter than its header"),
    ("k", "header"),
    ("flags", "header"),
    ("escapes", "escape"),
    ("nan_count", "nan_bits|NaN"),
    ("truncated", "do not fill"),
    ("frame", "part"),
    ("size", "part"),
    ("shape", "not valid"),
])
def test_a_malformed_filter_5_array_is_refused(bad: str, match: str) -> None:
    a = _noisy_surface("<f4", (30, 40), 1e-3, seed=5)
    a[2, 3:9] = np.nan
    a[7, 0] = 1e30  # an escape
    m = _split_msg(a)
    data: bytes = m.data  # type: ignore[attr-defined]
    head = E._IMAGE_HEADER.size
    lengths = E._IMAGE_HEADER.unpack_from(data)[4:]
    high_at = head + lengths[0] + lengths[1]
    if bad == "short":
        data = data[:10]
    elif bad == "k":
        data = _set_header(data, k=17)
    elif bad == "flags":
        data = _set_header(data, flags=0)
    elif bad == "escapes":
        data = _set_header(data, n_esc=E._IMAGE_HEADER.unpack_from(data)[2] + 1)
    elif bad == "nan_count":
        data = _set_header(data, n_nan=E._IMAGE_HEADER.unpack_from(data)[3] - 1)
    elif bad == "truncated":
        data = data[:-1]
    elif bad == "frame":  # the high part's zstd frame damaged
        data = data[:high_at] + b"\0\0\0\0" + data[high_at + 4:]
    elif bad == "size":  # a frame that holds another size than the part needs
        frame = zstandard.ZstdCompressor().compress(b"\0" * (30 * 40 + 1))
        rest = data[high_at + lengths[2]:]
        lengths = (*lengths[:2], len(frame), *lengths[3:])
        data = (E._IMAGE_HEADER.pack(*E._IMAGE_HEADER.unpack_from(data)[:4], *lengths)
                + data[head:high_at] + frame + rest)
    else:
        del m.shape[:]  # type: ignore[attr-defined]
        m.shape.extend([1200])  # type: ignore[attr-defined]
    m.data = data  # type: ignore[attr-defined]
    with pytest.raises(LogError, match=match):
        E.msg_to_array(m)


def test_the_range_record_keeps_every_bit_pattern() -> None:
    """NaN payloads, signed zeros, infinities, denormals (a Scan refuses some of these; the
    record does not care): the encoder reads only ``range``, ``index``, ``capture_time_ns``."""
    r = make_scan(3, (24, 32)).range.astype("<f4").copy()
    r.reshape(-1)[:len(SPECIAL_F4)] = SPECIAL_F4.view("<f4")
    r[5:9, :] = np.nan  # a run of no return
    data = E.encode_range(SimpleNamespace(range=r, index=3, capture_time_ns=5), 0)  # type: ignore[arg-type]
    assert E.is_range_record(data)
    assert E.decode_range(data).tobytes() == r.tobytes()


@pytest.mark.parametrize("bad", ["ndim1", "ndim3", "bytes", "empty", "short"])
def test_a_malformed_image_array_is_refused(bad: str) -> None:
    a = np.arange(12, dtype="<f4").reshape(3, 4)
    m = _array_msg()
    E.array_to_msg(m, "x", a, image=True)
    if bad == "ndim1":
        del m.shape[:]  # type: ignore[attr-defined]
        m.shape.append(12)  # type: ignore[attr-defined]
    elif bad == "ndim3":
        del m.shape[:]  # type: ignore[attr-defined]
        m.shape.extend([3, 2, 2])  # type: ignore[attr-defined]
    elif bad == "bytes":
        m.dtype = "|u1"  # type: ignore[attr-defined]
        del m.shape[:]  # type: ignore[attr-defined]
        m.shape.extend([6, 8])  # type: ignore[attr-defined]
    elif bad == "empty":
        del m.shape[:]  # type: ignore[attr-defined]
        m.shape.extend([0, 4])  # type: ignore[attr-defined]
        m.data = b""  # type: ignore[attr-defined]
    else:
        m.data = m.data[:-1]  # type: ignore[attr-defined]
    with pytest.raises(LogError):
        E.msg_to_array(m)


def test_a_malformed_range_record_is_refused() -> None:
    msg = message_class("Product")()
    msg.schema = E.record_schema(E.RANGE_RECORD)
    E.array_to_msg(msg.arrays.add(), "range", np.zeros((4, 5), "<f8"), image=True)
    with pytest.raises(LogError, match="malformed"):
        E.decode_range(msg.SerializeToString())


def _sim_scan() -> Scan:
    from boxloc.simulate import scene_suite, simulate

    return simulate(scene_suite(1, 0)[0]).scan


def _rawimage(scan: Scan, t_ns: int) -> bytes:
    """The range as schema 1.3 wrote it: a Foxglove RawImage 32FC1."""
    H, W = scan.shape
    msg = RawImage(frame_id=E.SENSOR_FRAME, width=W, height=H, encoding="32FC1", step=W * 4,
                   data=np.ascontiguousarray(scan.range, "<f4").tobytes())
    msg.timestamp.FromNanoseconds(t_ns)
    return msg.SerializeToString()


def test_the_range_record_takes_under_three_quarters_of_the_raw_image() -> None:
    """On a simulated 640 x 480 scan, compressed as the recorder compresses chunks: filter 5
    (schema 1.6) under 97 % of filter 4 (1.5; measured 95.9 %), which is under 75 % of
    the RawImage of 1.3."""
    scan = _sim_scan()
    assert scan.shape == (480, 640)
    z = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
    data = E.encode_range(scan, 0)
    legacy = E.legacy_range_message(data)
    new, v15, v13 = (len(z.compress(d)) for d in (data, legacy, _rawimage(scan, 0)))
    assert new < 0.97 * v15 and v15 < 0.75 * v13, (new, v15, v13)
    for d, filt in ((data, 5), (legacy, 4)):
        msg = message_class("Product")()
        msg.ParseFromString(d)
        assert [a.filter for a in msg.arrays] == [filt]
        assert E.decode_range(d).tobytes() == scan.range.tobytes()


def test_an_old_raw_image_range_still_decodes_bit_for_bit() -> None:
    scan = make_scan(1)
    data = _rawimage(scan, 123)
    assert not E.is_range_record(data)
    assert E.decode_range(data).tobytes() == scan.range.astype("<f4").tobytes()


def test_a_schema_1_3_log_reads_back(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A log written as 1.3 wrote it (RawImage range channel) gives the same scans."""
    scans = [make_scan(k) for k in range(2)]
    old = dataclasses.replace(C.BY_TOPIC[C.SCAN_RANGE], schema_name="foxglove.RawImage",
                              record=None, encoder=_rawimage)
    with monkeypatch.context() as mp:
        mp.setattr(E, "SCHEMA_VERSION", "1.3")
        mp.setattr(E, "encode_range", _rawimage)
        mp.setitem(C.BY_TOPIC, C.SCAN_RANGE, old)
        with McapRecorder(tmp_path / "old.mcap") as rec:
            for s in scans:
                feed(rec, s, make_result(s, s.index))
    with open(tmp_path / "old.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    schema = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert schema[C.SCAN_RANGE] == "foxglove.RawImage"
    back = list(open_log(tmp_path / "old.mcap").scans())
    assert [r.scan.range.tobytes() for r in back] == [s.range.tobytes() for s in scans]


@pytest.mark.parametrize("name", ["mixed-640x480.mcap", "pallet-320x240.mcap"])
def test_the_sample_logs_are_old_logs_and_read(name: str) -> None:
    path = ROOT / "logs" / name
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    schema = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert schema[C.SCAN_RANGE] == "foxglove.RawImage"
    recs = list(open_log(path).scans())
    assert recs and all(r.scan.range.dtype == np.float32 and np.isfinite(r.scan.range).any()
                        for r in recs)


def test_the_preview_is_a_jpeg_of_the_range_near_bright_no_return_black() -> None:
    scan = make_scan(2, (60, 80))
    msg = CompressedImage()
    msg.ParseFromString(E.encode_range_preview(scan, 7))
    assert msg.format == "jpeg" and msg.frame_id == E.SENSOR_FRAME
    img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img.shape == scan.shape and img.dtype == np.uint8  # 80 wide: full size
    r = scan.range
    ok = np.isfinite(r)
    near, far = r[ok] < np.quantile(r[ok], 0.2), r[ok] > np.quantile(r[ok], 0.8)
    assert img[ok][near].mean() > img[ok][far].mean() + 50
    if (~ok).any():
        assert img[~ok].mean() < img[ok].mean()
    big = make_scan(2, (480, 700))  # 700 wide: every third pixel, 234 wide
    msg.ParseFromString(E.encode_range_preview(big, 7))
    img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img.shape == (160, 234)
    empty = dataclasses.replace(scan, range=np.full(scan.shape, np.nan, np.float32))
    msg.ParseFromString(E.encode_range_preview(empty, 7))
    assert cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_UNCHANGED).max() <= 2


def test_the_view_clouds_lie_on_the_grid_within_half_a_step() -> None:
    scan = make_scan(4)
    msg = PointCloud()
    msg.ParseFromString(E.encode_points(scan, 0, 10**9))
    P = np.frombuffer(msg.data, "<f4").reshape(-1, 3).astype(np.float64)
    exact = scan.points.reshape(-1, 3)
    exact = exact[np.isfinite(exact).all(1)]
    assert P.shape == exact.shape
    assert np.abs(P - exact).max() <= E.VIEW_GRID / 2 + 1e-7
    k = P / E.VIEW_GRID
    assert np.array_equal(k, np.rint(k))


def test_log_footprint_splits_each_scans_bytes_by_channel(tmp_path: Path) -> None:
    from recorder.mcap.footprint import format_table, log_footprint

    scans = [make_scan(k, (60, 80)) for k in range(3)]
    with McapRecorder(tmp_path / "a.mcap") as rec:
        for s in scans:
            feed(rec, s, make_result(s, s.index))
    fp = log_footprint(tmp_path / "a.mcap")
    assert fp["scans"] == 3 and len(fp["scan_bytes"]) == 3
    assert fp["bytes_per_scan"] == (tmp_path / "a.mcap").stat().st_size / 3
    ch = fp["channels"]
    assert {C.SCAN_RANGE, C.SCAN_PREVIEW, C.EDGES, C.TESTS} <= set(ch)
    # the range's record is compressed already (filter 5): the chunk's zstd finds nothing
    assert ch[C.SCAN_RANGE]["zstd"] <= ch[C.SCAN_RANGE]["raw"] + 30 < 80 * 60 * 4
    zs = [c["zstd"] for c in ch.values()]
    assert zs == sorted(zs, reverse=True)  # largest first
    # compressed alone, the channels add up to about the chunks
    assert 0.8 < sum(zs) / (sum(fp["scan_bytes"]) / 3) < 1.3
    assert C.SCAN_RANGE in format_table(fp)


def test_footprint_command_names_a_missing_log_in_one_line(tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]
                                                           ) -> None:
    from recorder.mcap.footprint import main

    assert main(["--log", str(tmp_path / "none.mcap")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("footprint: error:") and len(err.strip().splitlines()) == 1


def test_the_matrix_suite_at_640x480_keeps_each_sensors_field_of_view() -> None:
    from boxloc.simulate import matrix_suite
    from recorder.mcap.footprint import suite

    for orig, s in zip(matrix_suite(8, 0), suite("matrix", 8)):
        assert (s.width, s.height) == (640, 480)
        assert s.f / s.width == pytest.approx(orig.f / orig.width, rel=1e-3)
        assert (s.kind, s.sensor, s.seed) == (orig.kind, orig.sensor, orig.seed)


@pytest.mark.parametrize("reader", [None, (1, 5), (1, 6)])
def test_a_log_copied_for_older_readers_holds_the_same_scans_and_products(
        tmp_path: Path, reader: tuple[int, int] | None) -> None:
    """``copy_log_for_older_readers``: for readers before 1.6 the range in filter 4, for
    readers before 1.7 every float64 array in filter 1 or 3, never 6 or 7; the same bits,
    and every other message as it was."""
    from recorder.mcap.sink import copy_log_for_older_readers

    scans = [make_scan(k, (40, 50)) for k in range(3)]
    scans[1].range.flags.writeable = True
    scans[1].range[5:7, 10:20] = np.nan
    src, dst = tmp_path / "new.mcap", tmp_path / "old.mcap"
    with McapRecorder(src) as rec:
        for s in scans:
            r = make_result(s, s.index)
            edges = r.edges  # the edge stage rounds to float32 precision; so does this
            r = dataclasses.replace(r, edges=dataclasses.replace(
                edges, points=float32_precision(edges.points),
                covariances=float32_precision(edges.covariances)))
            feed(rec, s, r)
    copy_log_for_older_readers(src, dst, reader)

    def messages(path: Path) -> list[tuple[str, int, bytes]]:
        with open(path, "rb") as f:
            return [(c.topic, m.log_time, m.data)
                    for _, c, m in make_reader(f).iter_messages(log_time_order=False)]

    def filters(d: bytes) -> list[int]:
        msg = message_class("Product")()
        msg.ParseFromString(d)
        return [arr.filter for arr in msg.arrays]

    products = {c.topic for c in C.CHANNELS if c.schema_name.endswith(".Product")}
    a, b = messages(src), messages(dst)
    assert [(t, lt) for t, lt, _ in a] == [(t, lt) for t, lt, _ in b]
    rewritten = set()
    for (topic, _, x), (_, _, y) in zip(a, b):
        if topic == C.SCAN_RANGE:
            assert filters(x) == [5] and filters(y) == [5 if reader == (1, 6) else 4]
            assert E.decode_range(x).tobytes() == E.decode_range(y).tobytes()
        elif topic in products and {6, 7} & set(filters(x)):
            rewritten.add(topic)
            assert not {6, 7} & set(filters(y))
            _, ax = E.decode_arrays(x, C.BY_TOPIC[topic].record or "")
            _, ay = E.decode_arrays(y, C.BY_TOPIC[topic].record or "")
            assert ax.keys() == ay.keys()
            assert all(ax[k].dtype == ay[k].dtype and ax[k].tobytes() == ay[k].tobytes()
                       for k in ax)
        else:
            assert x == y
    assert C.EDGES in rewritten
    back = [r.scan.range.tobytes() for r in open_log(dst).scans()]
    assert back == [s.range.tobytes() for s in scans]


@pytest.mark.parametrize("shape", [(64,), (70, 3), (30, 3, 3), (2, 40, 6, 6)])
def test_float64_arrays_of_float32_values_are_stored_as_float32_bit_for_bit(
        shape: tuple[int, ...]) -> None:
    """Filters 6 and 7 (schema 1.7): half the bytes, every bit back, special values too;
    a single value that is not a float32 keeps the array in float64."""
    rng = np.random.default_rng(len(shape))
    a = rng.normal(size=shape).astype(np.float32).astype(np.float64)
    flat = a.reshape(-1)
    flat[:7] = [np.nan, -0.0, np.inf, -np.inf, 1e-45, 3.4e38, 0.0]
    flat[:7] = flat[:7].astype(np.float32).astype(np.float64)
    sym = len(shape) >= 3
    if sym:
        a = 0.5 * (a + np.swapaxes(a, -1, -2))
        a = a.astype(np.float32).astype(np.float64)
    for f32, expect in ((True, 7 if sym else 6), (False, 3 if sym else 1)):
        m = _array_msg()
        E.array_to_msg(m, "x", a, float32=f32)
        assert m.filter == expect  # type: ignore[attr-defined]
        b = E.msg_to_array(m)
        assert b.dtype == np.float64 and b.shape == a.shape and b.tobytes() == a.tobytes()
        k = shape[-1]
        stored = a.size // (k * k) * k * (k + 1) // 2 if sym else a.size
        assert len(m.data) == stored * (4 if f32 else 8)  # type: ignore[attr-defined]
    c = a.copy()
    c.reshape(-1)[-1] = 0.1  # not a float32: the whole array stays float64
    m = _array_msg()
    E.array_to_msg(m, "x", c)
    assert m.filter in (1, 3) and E.msg_to_array(m).tobytes() == c.tobytes()  # type: ignore


@pytest.mark.parametrize("dtype,shape,data,filt", [
    ("<f4", (64,), 256, 6), ("<f8", (64,), 512, 6), ("<f8", (64,), 255, 6),
    ("<i8", (64,), 256, 6), ("<f8", (10, 3, 2), 240, 7), ("<f8", (10, 3, 3), 360, 7),
    ("<f4", (10, 3, 3), 240, 7)])
def test_a_malformed_float32_array_is_refused(dtype: str, shape: tuple[int, ...],
                                              data: int, filt: int) -> None:
    """Filters 6 and 7 only on float64 (7: stacks of square matrices), with exactly the
    float32 bytes their shape needs (7: 10 x 6 upper-triangle values are 240 bytes)."""
    m = _array_msg()
    m.name, m.dtype, m.data = "x", dtype, b"\0" * data  # type: ignore[attr-defined]
    m.shape.extend(shape)  # type: ignore[attr-defined]
    m.filter = filt  # type: ignore[attr-defined]
    with pytest.raises(LogError):
        E.msg_to_array(m)
    if (dtype, shape) == ("<f8", (10, 3, 3)):
        m.data = b"\0" * 240  # type: ignore[attr-defined]
        assert not E.msg_to_array(m).any()


def test_the_edge_map_and_vertex_tests_are_float32_in_the_log() -> None:
    """What the pipeline rounds (edge points, covariances, jump heights, p-values, the
    line-pair statistics) is stored as float32; the scan's products read back bit for bit."""
    from boxloc.config import Config
    from boxloc.pipeline import find_graspable_surfaces
    from boxloc.products import products_equal

    scan = make_scan(3, (120, 160))
    res = find_graspable_surfaces(scan, Config())
    e = res.edges
    assert len(e) > 0
    for a in (e.points, e.covariances, e.strength, e.tests.p_value, res.vertices.tests.statistic):
        assert a.tobytes() == a.astype(np.float32).astype(np.float64).tobytes()
    msg = message_class("Product")()
    msg.ParseFromString(E.encode_product("edges", e, 0, 0))
    f = {arr.name: arr.filter for arr in msg.arrays}
    assert f["points"] == 6 and f["covariances"] == 7
    tests = E.decode_test_columns(E.encode_test_rows(0, {"edges": e.tests}))["edges"]
    back = E.decode_product("edges", E.encode_product("edges", e, 0, 0), tests)
    assert products_equal(back, e) == []


def test_damaged_filter_5_data_is_refused_or_decodes_never_raises_otherwise() -> None:
    """Logs are untrusted: a flipped byte or a cut anywhere in the data gives a LogError or
    an array of the declared shape, never another exception."""
    a = _noisy_surface("<f4", (24, 32), 1e-3, seed=9)
    a[3, 5:12] = np.nan
    a[9, 0] = 1e30
    m = _split_msg(a)
    good: bytes = m.data  # type: ignore[attr-defined]
    rng = np.random.default_rng(11)
    outcomes = {"refused": 0, "decoded": 0}
    for trial in range(300):
        data = bytearray(good)
        if trial % 3 == 0:
            data = data[: int(rng.integers(0, len(data)))]
        else:
            for _ in range(int(rng.integers(1, 4))):
                data[int(rng.integers(0, len(data)))] ^= int(rng.integers(1, 256))
        m.data = bytes(data)  # type: ignore[attr-defined]
        try:
            b = E.msg_to_array(m)
        except LogError:
            outcomes["refused"] += 1
        else:
            assert b.shape == a.shape and b.dtype == a.dtype
            outcomes["decoded"] += 1
    assert outcomes["refused"] > 100, outcomes

"""Property tests of the scan readers and the scan model (hypothesis): any array, any header,
any damaged file ends in a Scan or in an InputError with a one-line message, never another
exception, and what is accepted is what was given. Also a small fuzz campaign through
``boxloc bench --fuzz N`` (the full one runs 10,000 cases; see docs/reliability.md).
"""

from __future__ import annotations

import io
import json
import tracemalloc
import warnings
import zipfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from boxloc.cli import cli
from boxloc.config import Config
from boxloc.errors import InputError
from boxloc.io import parse_intrinsics, read_scan, write_npz
from boxloc.pipeline import find_graspable_surfaces
from boxloc.scan import PinholeModel, RayTableModel, Scan
from recorder.fuzz import CATEGORIES, PICKLE_BOMB, mutate_bytes, pcd_bytes, ply_bytes

CI = settings(max_examples=40, deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow,
                                     HealthCheck.function_scoped_fixture])
H, W = 12, 16
INTR = (14.0, 14.0, 7.5, 5.5)
INTR_S = "14,14,7.5,5.5"


def one_line(e: BaseException) -> None:
    msg = str(e)
    assert msg.strip() and "\n" not in msg, repr(msg)


DTYPES = st.one_of(
    hnp.floating_dtypes(sizes=(16, 32, 64)), hnp.integer_dtypes(), hnp.unsigned_integer_dtypes(),
    hnp.boolean_dtypes(), hnp.complex_number_dtypes(), hnp.unicode_string_dtypes(max_len=3),
    hnp.datetime64_dtypes(),
)
SHAPES = hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=7)


@st.composite
def any_array(draw: Any, shapes: Any = SHAPES) -> np.ndarray:
    dt = draw(DTYPES)
    shape = draw(shapes)
    if dt.kind == "f":
        # NaN and inf storms: the special values are drawn much more often than by chance
        elems = st.one_of(st.sampled_from([np.nan, np.inf, -np.inf, 0.0, -0.0, 1e-45, 3e38]),
                          st.floats(allow_nan=True, allow_infinity=True,
                                    width=min(dt.itemsize * 8, 64)))
        return draw(hnp.arrays(dt, shape, elements=elems))
    return draw(hnp.arrays(dt, shape))


RANGE_SHAPES = st.one_of(SHAPES, hnp.array_shapes(min_dims=2, max_dims=2, min_side=0,
                                                   max_side=7))
POINT_SHAPES = st.one_of(SHAPES, st.tuples(st.integers(0, 6), st.integers(0, 6),
                                           st.sampled_from([3, 3, 3, 2])))


def _expected_range(a: np.ndarray) -> np.ndarray:
    r = a.astype(np.float32)
    return np.where(r == 0, np.float32(np.nan), r)


@CI
@given(any_array(RANGE_SHAPES))
def test_a_scan_of_any_range_array_is_made_or_refused(a: np.ndarray) -> None:
    hw = a.shape if a.ndim == 2 and min(a.shape) > 0 else (1, 1)
    sensor = PinholeModel(20.0, 20.0, hw[1] / 2, hw[0] / 2, hw[1], hw[0])
    try:
        scan = Scan(range=a, sensor=sensor)
    except InputError as e:
        one_line(e)
        return
    assert a.dtype.kind == "f" and scan.shape == a.shape
    r = scan.range
    assert r.dtype == np.float32 and not r.flags.writeable
    assert not np.isinf(r).any() and not (r <= 0).any()
    assert np.array_equal(r, _expected_range(a), equal_nan=True)
    assert scan.points.shape == (*a.shape, 3)
    assert np.array_equal(np.isfinite(scan.points).all(-1), np.isfinite(r))


def test_points_beyond_float32_are_refused_without_a_warning() -> None:
    # finite in float64, but their range overflows float32: refused in one line, and the
    # cast's overflow is not printed as a RuntimeWarning (a fuzzed scan file showed one)
    P = np.full((4, 4, 3), 1e38)
    P[..., 2] = 1e39
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match="found inf") as info:
            Scan.from_points(P)
    one_line(info.value)


@CI
@given(any_array(POINT_SHAPES))
def test_a_scan_from_any_points_array_is_made_or_refused(P: np.ndarray) -> None:
    try:
        scan = Scan.from_points(P)
    except InputError as e:
        one_line(e)
        return
    assert P.dtype.kind == "f" and P.ndim == 3 and P.shape[2] == 3
    Q = P.astype(np.float64)
    with np.errstate(all="ignore"):
        r32 = np.linalg.norm(np.nan_to_num(Q), axis=-1).astype(np.float32)
    ok = np.isfinite(Q).all(-1) & (r32 > 0)
    assert scan.shape == P.shape[:2]
    # A pixel has a return exactly where the input had a finite point whose range is not 0
    # in float32 (a range that overflows float32 would have been refused).
    assert np.array_equal(scan.valid, ok)


@CI
@given(any_array(hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=5)))
def test_a_ray_table_of_any_array_is_made_or_refused(T: np.ndarray) -> None:
    try:
        model = RayTableModel(T)
        scan = Scan(range=np.full(model.shape, 1.5, np.float32), sensor=model)
    except InputError as e:
        one_line(e)
        return
    # a pixel without a ray has no return
    assert np.array_equal(scan.valid, np.isfinite(model.table).all(-1))
    assert np.isfinite(model.pixel_angle)


@CI
@given(any_array(RANGE_SHAPES))
def test_an_npz_of_any_range_array_reads_or_is_refused(tmp_path: Path, a: np.ndarray) -> None:
    p = tmp_path / "a.npz"
    np.savez(p, range=a, intrinsics=np.array([[14.0, 0, 7.5], [0, 14.0, 5.5], [0, 0, 1]]))
    try:
        scan = read_scan(p)
    except InputError as e:
        one_line(e)
        return
    assert np.array_equal(scan.range, _expected_range(a), equal_nan=True)


DESCRS = ["<f4", "<f8", ">f4", "<f2", "|O", "<c16", "|b1", "<i8", "<u8", "<U4", "|V16", "<M8[ns]",
          "|S3", "<f16"]


@CI
@given(st.lists(st.integers(-(2**63), 2**64), min_size=0, max_size=5),
       st.sampled_from(DESCRS), st.sampled_from(["range", "points", "intrinsics"]),
       st.binary(max_size=64))
def test_an_npy_header_claiming_anything_is_refused_before_loading(
        tmp_path: Path, shape: list[int], descr: str, key: str, tail: bytes) -> None:
    f = io.BytesIO()
    np.lib.format.write_array_header_1_0(f, {"descr": descr, "fortran_order": False,
                                             "shape": tuple(shape)})
    payload = PICKLE_BOMB if descr == "|O" else tail
    p = tmp_path / "h.npz"
    with zipfile.ZipFile(p, "w") as zf:
        zf.writestr(f"{key}.npy", f.getvalue() + payload)
        if key != "intrinsics":
            zf.writestr("intrinsics.npy", _npy(np.eye(3) * 14))
        else:
            zf.writestr("range.npy", _npy(np.ones((H, W), np.float32)))
    tracemalloc.start()
    try:
        with pytest.raises(InputError) as info:
            read_scan(p)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    one_line(info.value)
    assert peak < 16 * 2**20  # nothing like the declared size was allocated
    assert not (Path.cwd() / "PWNED").exists()


def _npy(a: np.ndarray) -> bytes:
    f = io.BytesIO()
    np.lib.format.write_array(f, a, allow_pickle=False)
    return f.getvalue()


@pytest.fixture(scope="module")
def good_files(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[Path, dict[str, Any]]]:
    """One valid scan in every format the readers take."""
    d = tmp_path_factory.mktemp("good")
    sensor = PinholeModel(*INTR, width=W, height=H)
    n = np.array([0.1, -0.3, -1.0])
    n /= np.linalg.norm(n)
    r = (n @ np.array([0.0, 0.0, 1.5])) / (sensor.rays() @ n)
    r[2, 3] = np.nan
    scan = Scan(range=r.astype(np.float32), sensor=sensor)
    z = scan.points[..., 2]
    files: list[tuple[Path, dict[str, Any]]] = []
    write_npz(scan, d / "s.npz")
    files.append((d / "s.npz", {}))
    cv2.imwrite(str(d / "d.png"), np.nan_to_num(np.round(z * 1000)).astype(np.uint16))
    files.append((d / "d.png", {"intrinsics": INTR_S, "depth_scale": 0.001}))
    cv2.imwrite(str(d / "d.tiff"), z.astype(np.float32))
    files.append((d / "d.tiff", {"intrinsics": INTR_S}))
    for kind in ("ascii", "binary", "binary_compressed"):
        (d / f"{kind}.pcd").write_bytes(pcd_bytes(scan.points, kind))
        files.append((d / f"{kind}.pcd", {}))
    for fmt in ("ascii", "binary_little_endian"):
        (d / f"{fmt}.ply").write_bytes(ply_bytes(scan.points, fmt))
        files.append((d / f"{fmt}.ply", {}))
    for p, kw in files:  # every one of them reads
        assert read_scan(p, **kw).shape == (H, W)
    return files


@CI
@given(data=st.data())
def test_a_damaged_scan_file_reads_or_is_refused(tmp_path: Path, data: Any,
                                                 good_files: list[tuple[Path, dict[str, Any]]]
                                                 ) -> None:
    src, kw = data.draw(st.sampled_from(good_files), label="file")
    seed = data.draw(st.integers(0, 2**32 - 1), label="seed")
    rng = np.random.default_rng(seed)
    raw, op = mutate_bytes(rng, src.read_bytes())
    p = tmp_path / f"m{src.suffix}"
    p.write_bytes(raw)
    try:
        scan = read_scan(p, **kw)
    except InputError as e:
        one_line(e)
        return
    assert scan.range.dtype == np.float32 and not np.isinf(scan.range).any()


@settings(max_examples=200, deadline=None, derandomize=True, database=None)
@given(st.one_of(st.text(max_size=40), st.lists(st.floats(), max_size=10)))
def test_intrinsics_of_any_text_or_numbers(value: Any) -> None:
    try:
        fx, fy, cx, cy = parse_intrinsics(value)  # type: ignore[misc]
    except InputError as e:
        one_line(e)
        return
    assert fx > 0 and fy > 0 and np.isfinite([fx, fy, cx, cy]).all()


@st.composite
def degenerate_scan(draw: Any) -> Scan:
    """A tiny scan: a plane (or nothing) seen through a random mask of valid pixels."""
    h, w = draw(st.integers(1, 10)), draw(st.integers(1, 12))
    f = draw(st.sampled_from([0.8 * w + 1, 1e-3, 1e5]))
    sensor = PinholeModel(f, f, (w - 1) / 2, (h - 1) / 2, w, h)
    tilt = draw(st.floats(-0.5, 0.5))
    n = np.array([tilt, 0.0, -1.0]) / np.hypot(tilt, 1.0)
    with np.errstate(all="ignore"):
        r = (n @ np.array([0.0, 0.0, draw(st.sampled_from([1e-6, 1.5, 1e6]))])) / (
            sensor.rays() @ n)
    mask = draw(hnp.arrays(np.bool_, (h, w)))
    r = np.where(mask, r, np.nan).astype(np.float32)
    return Scan(range=r, sensor=sensor)


@settings(max_examples=30, deadline=None, derandomize=True, database=None)
@given(degenerate_scan())
def test_the_pipeline_on_tiny_degenerate_scans(scan: Scan) -> None:
    try:
        res = find_graspable_surfaces(scan, Config())
    except InputError as e:  # only a scan without any return is refused
        one_line(e)
        assert not scan.valid.any()
        return
    s = res.surfaces
    assert len(s) <= 1 or np.isfinite(np.asarray(s.centers)).all()


def test_a_small_fuzz_campaign_through_the_bench(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """`boxloc bench --fuzz N`: every category, no failure (CI size; the README's figures
    come from 10,000 cases). ``--out`` is relative: the workers change directory."""
    monkeypatch.chdir(tmp_path.parent)
    res = CliRunner().invoke(cli, ["bench", "--fuzz", "42", "--seed", "5", "--out",
                                   tmp_path.name], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    report = json.loads((tmp_path / "bench.json").read_text())
    assert report["errors"]["total"] == 0, report["errors"]
    fz = report["sections"]["fuzz"]
    assert fz["cases"] == 42
    assert set(fz["by_category"]) == set(CATEGORIES)
    assert all(v["cases"] >= 2 for v in fz["by_category"].values())
    assert fz["outcomes"]["failure"] == 0, fz["failures"]
    assert fz["outcomes"]["ok"] > 0 and fz["outcomes"]["error"] > 0

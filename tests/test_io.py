"""Scan readers and the .npz writer: formats, round trips, and every kind of bad input."""

from __future__ import annotations

import struct
import subprocess
import sys
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest
from cli_run import invoke
from real_data import MOSD

from boxloc.errors import InputError
from boxloc.io import (
    SUPPORTED_SUFFIXES,
    parse_intrinsics,
    range_from_depth,
    read_labels,
    read_scan,
    read_scans,
    write_npz,
)
from boxloc.scan import PinholeModel, RayTableModel, Scan

H, W = 24, 32
INTR = (40.0, 42.0, 15.5, 11.5)
INTR_S = "40,42,15.5,11.5"


def plane_scan(seed: int = 0, *, nan_frac: float = 0.1, **kw: object) -> Scan:
    """A tilted plane about 1.5 m away, with a few dropouts."""
    rng = np.random.default_rng(seed)
    sensor = PinholeModel(*INTR, width=W, height=H)
    rays = sensor.rays()
    n = np.array([0.0, -0.3, -1.0])
    n /= np.linalg.norm(n)
    r = (n @ np.array([0.0, 0.0, 1.5])) / (rays @ n)
    r = r + rng.normal(0, 1e-3, r.shape)
    r[rng.random(r.shape) < nan_frac] = np.nan
    return Scan(range=r.astype(np.float32), sensor=sensor, **kw)  # type: ignore[arg-type]


def same_range(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype == np.float32 and a.tobytes() == b.tobytes()


# --- .npz -------------------------------------------------------------------------------


def test_npz_round_trip_is_bit_exact(tmp_path: Path) -> None:
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 1.3]
    scan = plane_scan(capture_time_ns=1_700_000_000_123_456_789, sensor_to_base=T)
    p = tmp_path / "s.npz"
    write_npz(scan, p)
    back = read_scan(p, index=7)
    assert same_range(back.range, scan.range)
    assert back.sensor == scan.sensor
    assert back.capture_time_ns == scan.capture_time_ns
    assert back.index == 7
    assert back.sensor_to_base is not None and back.sensor_to_base.tobytes() == T.tobytes()
    assert back.source == str(p)
    # The public layout.
    with np.load(p, allow_pickle=False) as z:
        assert set(z.files) == {"range", "points", "intrinsics", "capture_time_ns",
                                "sensor_to_base"}
        assert z["range"].dtype == np.float32 and z["range"].shape == (H, W)
        assert z["points"].dtype == np.float32 and z["points"].shape == (H, W, 3)
        np.testing.assert_array_equal(z["intrinsics"], scan.sensor.K)
        assert z["capture_time_ns"].shape == () and z["capture_time_ns"].dtype.kind == "i"
        assert np.array_equal(z["points"], scan.points, equal_nan=True)


def test_npz_is_deterministic_and_minimal(tmp_path: Path) -> None:
    scan = plane_scan()
    write_npz(scan, tmp_path / "a.npz")
    write_npz(scan, tmp_path / "b.npz")
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    with np.load(tmp_path / "a.npz") as z:
        assert "sensor_to_base" not in z.files
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "b.npz"]  # no temp left


def test_npz_raytable_round_trip(tmp_path: Path) -> None:
    base = plane_scan(nan_frac=0.0)
    table = base.sensor.rays().copy()
    table[..., 0] += 0.2 * table[..., 1] ** 2  # bent: not a pinhole any more
    scan = Scan(range=base.range, sensor=RayTableModel(table))
    write_npz(scan, tmp_path / "r.npz")
    with np.load(tmp_path / "r.npz") as z:
        assert "intrinsics" not in z.files
    back = read_scan(tmp_path / "r.npz")
    assert same_range(back.range, scan.range)
    assert isinstance(back.sensor, RayTableModel)
    np.testing.assert_allclose(back.sensor.table, scan.sensor.table, atol=1e-6)


def test_npz_points_only_fits_pinhole(tmp_path: Path) -> None:
    scan = plane_scan()
    np.savez(tmp_path / "p.npz", points=scan.points)
    back = read_scan(tmp_path / "p.npz")
    assert isinstance(back.sensor, PinholeModel)
    np.testing.assert_allclose(
        [back.sensor.fx, back.sensor.fy, back.sensor.cx, back.sensor.cy], INTR, atol=1e-3)
    np.testing.assert_allclose(back.range, scan.range, rtol=1e-6)
    assert np.array_equal(np.isnan(back.range), np.isnan(scan.range))


def test_npz_points_with_intrinsics_option(tmp_path: Path) -> None:
    scan = plane_scan()
    np.savez(tmp_path / "p.npz", points=scan.points)
    back = read_scan(tmp_path / "p.npz", intrinsics=INTR_S)
    assert back.sensor == scan.sensor
    with pytest.raises(InputError, match="do not fit the points"):
        read_scan(tmp_path / "p.npz", intrinsics="60,42,15.5,11.5")


def test_npz_range_intrinsics_and_unknown_keys(tmp_path: Path) -> None:
    scan = plane_scan()
    np.savez(tmp_path / "s.npz", range=scan.range.astype(np.float64), intrinsics=scan.sensor.K,
             **{"truth/boxes": np.zeros((2, 8)), "extra": np.arange(3)})
    back = read_scan(tmp_path / "s.npz")
    assert same_range(back.range, scan.range)
    assert back.sensor == scan.sensor
    assert back.capture_time_ns == 0 and back.sensor_to_base is None


def test_npz_range_needs_intrinsics_from_option(tmp_path: Path) -> None:
    scan = plane_scan()
    np.savez(tmp_path / "s.npz", range=scan.range)
    with pytest.raises(InputError, match="pass --intrinsics"):
        read_scan(tmp_path / "s.npz")
    back = read_scan(tmp_path / "s.npz", intrinsics=INTR_S)
    assert back.sensor == scan.sensor and same_range(back.range, scan.range)


def test_npz_intrinsics_option_must_agree(tmp_path: Path) -> None:
    write_npz(plane_scan(), tmp_path / "s.npz")
    assert read_scan(tmp_path / "s.npz", intrinsics=INTR).sensor.fx == INTR[0]
    with pytest.raises(InputError, match="conflicts with the intrinsics stored"):
        read_scan(tmp_path / "s.npz", intrinsics="41,42,15.5,11.5")


def test_reader_accepts_all_nan_scan(tmp_path: Path) -> None:
    # Documented choice: readers accept it; the pipeline's check_scan refuses it.
    scan = plane_scan(nan_frac=1.0)
    write_npz(scan, tmp_path / "n.npz")
    assert np.isnan(read_scan(tmp_path / "n.npz").range).all()


# --- depth images -----------------------------------------------------------------------


def test_png_16bit_millimetres(tmp_path: Path) -> None:
    import cv2

    sensor = PinholeModel(*INTR, width=W, height=H)
    v, u = np.mgrid[0:H, 0:W]
    z_mm = (1200 + 10 * u + 5 * v).astype(np.uint16)
    z_mm[3, 4] = 0  # no return
    assert cv2.imwrite(str(tmp_path / "d.png"), z_mm)
    scan = read_scan(tmp_path / "d.png", intrinsics=INTR_S, depth_scale=0.001)
    assert scan.sensor == sensor
    assert np.isnan(scan.range[3, 4]) and np.isfinite(scan.range).sum() == H * W - 1
    # Depth is z, so the points' z must equal depth * scale, and range = |point|.
    P = scan.points.astype(np.float64)
    ok = np.isfinite(P[..., 2])
    np.testing.assert_allclose(P[..., 2][ok], z_mm[ok] * 0.001, rtol=1e-6)
    # Corner pixel: range = z * |((u - cx)/fx, (v - cy)/fy, 1)|.
    want = 1.2 * np.sqrt((0 - 15.5) ** 2 / 40.0**2 + (0 - 11.5) ** 2 / 42.0**2 + 1)
    assert scan.range[0, 0] == pytest.approx(want, rel=1e-6)


def test_float_tiff_metres(tmp_path: Path) -> None:
    import cv2

    z = np.full((H, W), 0.8, dtype=np.float32)
    z[0, 0], z[1, 1], z[2, 2] = 0.0, np.nan, -1.0
    assert cv2.imwrite(str(tmp_path / "d.tiff"), z)
    scan = read_scan(tmp_path / "d.tiff", intrinsics=INTR_S)  # float: scale 1.0 by default
    assert np.isnan(scan.range[[0, 1, 2], [0, 1, 2]]).all()
    expect = range_from_depth(np.where(z > 0, z, np.nan), scan.sensor)
    assert np.array_equal(scan.range, expect, equal_nan=True)
    np.testing.assert_allclose(scan.points[5, 5, 2], 0.8, rtol=1e-6)
    half = read_scan(tmp_path / "d.tiff", intrinsics=INTR_S, depth_scale=0.5)
    np.testing.assert_allclose(half.range, scan.range * 0.5, rtol=1e-6)


# --- point clouds -----------------------------------------------------------------------


def _o3d_cloud(P: np.ndarray):  # type: ignore[no-untyped-def]
    import open3d as o3d

    return o3d.t.geometry.PointCloud(o3d.core.Tensor(P.reshape(-1, 3).astype(np.float32)))


def write_pcd(path: Path, P: np.ndarray, *, ascii: bool, compressed: bool) -> None:
    """Write with Open3D (which writes HEIGHT 1), then give the header the organization."""
    import open3d as o3d

    assert o3d.t.io.write_point_cloud(str(path), _o3d_cloud(P), write_ascii=ascii,
                                      compressed=compressed)
    raw = path.read_bytes()
    n = P.shape[0] * P.shape[1]
    old = f"WIDTH {n}\nHEIGHT 1\n".encode()
    assert old in raw
    path.write_bytes(raw.replace(old, f"WIDTH {P.shape[1]}\nHEIGHT {P.shape[0]}\n".encode(), 1))


def write_ply_o3d(path: Path, P: np.ndarray, *, ascii: bool = False) -> None:
    """Write with Open3D, then add the Stanford range-grid size to the header."""
    import open3d as o3d

    assert o3d.t.io.write_point_cloud(str(path), _o3d_cloud(P), write_ascii=ascii)
    raw = path.read_bytes()
    i = raw.index(b"\n", raw.index(b"format")) + 1
    info = f"obj_info num_cols {P.shape[1]}\nobj_info num_rows {P.shape[0]}\n".encode()
    path.write_bytes(raw[:i] + info + raw[i:])


@pytest.mark.parametrize("ascii,compressed", [(True, False), (False, False), (False, True)],
                         ids=["ascii", "binary", "binary_compressed"])
def test_pcd_organized_with_nans(tmp_path: Path, ascii: bool, compressed: bool) -> None:
    scan = plane_scan(nan_frac=0.2)
    p = tmp_path / "c.pcd"
    write_pcd(p, scan.points, ascii=ascii, compressed=compressed)
    back = read_scan(p)
    assert back.shape == (H, W)
    assert np.array_equal(np.isnan(back.range), np.isnan(scan.range))
    np.testing.assert_allclose(back.points, scan.points, rtol=1e-6, atol=1e-6)
    assert isinstance(back.sensor, PinholeModel)
    assert back.sensor.fx == pytest.approx(INTR[0], abs=1e-3)


@pytest.mark.parametrize("ascii", [False, True], ids=["binary", "ascii"])
def test_ply_organized_with_nans(tmp_path: Path, ascii: bool) -> None:
    scan = plane_scan(nan_frac=0.2)
    p = tmp_path / "c.ply"
    write_ply_o3d(p, scan.points, ascii=ascii)
    back = read_scan(p, intrinsics=INTR_S)
    assert back.sensor == scan.sensor
    assert np.array_equal(np.isnan(back.range), np.isnan(scan.range))
    # Open3D writes ascii PLY with ~7 significant digits.
    np.testing.assert_allclose(back.range, scan.range, rtol=1e-5 if ascii else 1e-6)


def _ply_range_grid(path: Path, P: np.ndarray, *, binary: bool) -> None:
    """A PCL/Stanford range-grid PLY: only valid vertices, plus a pixel -> vertex table."""
    flat = P.reshape(-1, 3)
    ok = np.isfinite(flat).all(1)
    verts = flat[ok].astype("<f4")
    idx = np.full(len(flat), -1)
    idx[ok] = np.arange(ok.sum())
    head = ("ply\nformat {}\ncomment test\nobj_info num_cols {}\nobj_info num_rows {}\n"
            "element vertex {}\nproperty float x\nproperty float y\nproperty float z\n"
            "element face 0\nproperty list uchar int vertex_indices\n"
            "element range_grid {}\nproperty list uchar int vertex_indices\nend_header\n")
    fmt = "binary_little_endian 1.0" if binary else "ascii 1.0"
    out = head.format(fmt, P.shape[1], P.shape[0], len(verts), len(flat)).encode()
    if binary:
        out += verts.tobytes()
        out += b"".join(struct.pack("<Bi", 1, i) if i >= 0 else b"\x00" for i in idx)
    else:
        out += "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in verts.tolist()).encode()
        out += "".join(f"1 {i}\n" if i >= 0 else "0\n" for i in idx).encode()
    path.write_bytes(out)


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "ascii"])
def test_ply_range_grid(tmp_path: Path, binary: bool) -> None:
    scan = plane_scan(nan_frac=0.3)
    p = tmp_path / "g.ply"
    _ply_range_grid(p, scan.points, binary=binary)
    back = read_scan(p, intrinsics=INTR_S)
    assert np.array_equal(np.isnan(back.range), np.isnan(scan.range))
    np.testing.assert_allclose(back.range, scan.range, rtol=1e-6)


def test_ply_pcl_camera_element(tmp_path: Path) -> None:
    scan = plane_scan(nan_frac=0.2)
    flat = scan.points.reshape(-1, 3).astype("<f4")
    floats = ["view_px", "view_py", "view_pz", "x_axisx", "x_axisy", "x_axisz", "y_axisx",
              "y_axisy", "y_axisz", "z_axisx", "z_axisy", "z_axisz", "focal", "scalex",
              "scaley", "centerx", "centery"]
    head = ("ply\nformat binary_little_endian 1.0\ncomment PCL generated\n"
            f"element vertex {len(flat)}\nproperty float x\nproperty float y\n"
            "property float z\nelement face 0\nproperty list uchar int vertex_indices\n"
            "element camera 1\n" + "".join(f"property float {f}\n" for f in floats)
            + "property int viewportx\nproperty int viewporty\nproperty float k1\n"
            "property float k2\nend_header\n")
    cam = struct.pack("<17f2i2f", *([0.0] * 17), W, H, 0.0, 0.0)
    (tmp_path / "cam.ply").write_bytes(head.encode() + flat.tobytes() + cam)
    back = read_scan(tmp_path / "cam.ply")
    assert back.shape == (H, W)
    assert np.array_equal(np.isnan(back.range), np.isnan(scan.range))


def test_pcd_viewpoint_is_undone(tmp_path: Path) -> None:
    scan = plane_scan(nan_frac=0.0)
    p = tmp_path / "v.pcd"
    # Points in a cloud frame where the sensor sits at t, turned 90 deg about z.
    t = np.array([1.0, 2.0, 3.0])
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    Pc = scan.points.astype(np.float64) @ R.T + t
    write_pcd(p, Pc, ascii=False, compressed=False)
    raw = p.read_bytes()
    q = np.sqrt(0.5)  # (w, x, y, z) for +90 deg about z
    p.write_bytes(raw.replace(b"VIEWPOINT 0 0 0 1 0 0 0",
                              f"VIEWPOINT 1 2 3 {q} 0 0 {q}".encode(), 1))
    back = read_scan(p)
    np.testing.assert_allclose(back.points, scan.points, atol=1e-5)
    assert back.meta["pcd_viewpoint"].shape == (4, 4)


def test_read_scans_directory(tmp_path: Path) -> None:
    for name, seed in (("b.npz", 1), ("a.npz", 0), ("c.npz", 2)):
        write_npz(plane_scan(seed), tmp_path / name)
    (tmp_path / "notes.txt").write_text("not a scan")
    scans = list(read_scans(tmp_path))
    assert [Path(s.source).name for s in scans] == ["a.npz", "b.npz", "c.npz"]
    assert [s.index for s in scans] == [0, 1, 2]
    assert same_range(scans[1].range, plane_scan(1).range)
    one = list(read_scans(tmp_path / "b.npz", index=4))
    assert len(one) == 1 and one[0].index == 4
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no scan files"):
        list(read_scans(tmp_path / "empty"))


def test_parse_intrinsics_forms() -> None:
    assert parse_intrinsics(None) is None
    assert parse_intrinsics(" 525, 525 ,319.5,239.5 ") == (525.0, 525.0, 319.5, 239.5)
    assert parse_intrinsics([1, 2, 3, 4]) == (1.0, 2.0, 3.0, 4.0)
    K = np.array([[5.0, 0, 1], [0, 6, 2], [0, 0, 1]])
    assert parse_intrinsics(K) == (5.0, 6.0, 1.0, 2.0)
    assert ".npz" in SUPPORTED_SUFFIXES and ".pcd" in SUPPORTED_SUFFIXES


# --- bad input --------------------------------------------------------------------------


def _zip_with(path: Path, members: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w") as zf:
        for k, v in members.items():
            zf.writestr(k, v)
    return path


def _npy_header_only(shape: tuple[int, ...], descr: str = "<f4") -> bytes:
    import io

    f = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        f, {"descr": descr, "fortran_order": False, "shape": shape})
    return f.getvalue()


def _npy(a: np.ndarray) -> bytes:
    import io

    f = io.BytesIO()
    np.lib.format.write_array(f, a, allow_pickle=True)
    return f.getvalue()


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(
        ">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def _case_files(tmp: Path, case: str) -> tuple[Path, dict[str, object]]:
    """Build the bad input of one case; return (path, read_scan keyword arguments)."""
    import cv2

    good = plane_scan()
    K = good.sensor.K
    npz = tmp / "s.npz"
    if case == "missing":
        return tmp / "nope.npz", {}
    if case == "directory":
        return tmp, {}
    if case == "suffix":
        (tmp / "s.xyz").write_text("1 2 3\n")
        return tmp / "s.xyz", {}
    if case == "npz_garbage":
        npz.write_bytes(b"this is not a zip file at all")
        return npz, {}
    if case == "npz_truncated":
        write_npz(good, npz)
        npz.write_bytes(npz.read_bytes()[: npz.stat().st_size // 2])
        return npz, {}
    if case == "npz_corrupt_member":
        return _zip_with(npz, {"range.npy": b"\x93NUMPY garbage", "intrinsics.npy": _npy(K)}), {}
    if case == "npz_short_member":
        data = _npy(good.range)[:-100]
        return _zip_with(npz, {"range.npy": data, "intrinsics.npy": _npy(K)}), {}
    if case == "npz_no_keys":
        np.savez(npz, foo=np.zeros(3))
        return npz, {}
    if case == "npz_range_3d":
        np.savez(npz, range=np.zeros((H, W, 1), np.float32), intrinsics=K)
        return npz, {}
    if case == "npz_range_int":
        np.savez(npz, range=np.ones((H, W), np.int32), intrinsics=K)
        return npz, {}
    if case == "npz_pickled":
        obj = np.empty((H, W), dtype=object)
        return _zip_with(npz, {"range.npy": _npy(obj), "intrinsics.npy": _npy(K)}), {}
    if case == "npz_points_shape":
        np.savez(npz, points=np.zeros((H, W, 2), np.float32))
        return npz, {}
    if case == "npz_intrinsics_shape":
        np.savez(npz, range=good.range, intrinsics=np.eye(4))
        return npz, {}
    if case == "npz_intrinsics_nonfinite":
        Kb = K.copy()
        Kb[0, 0] = np.inf
        np.savez(npz, range=good.range, intrinsics=Kb)
        return npz, {}
    if case == "npz_pose_shape":
        np.savez(npz, range=good.range, intrinsics=K, sensor_to_base=np.eye(3))
        return npz, {}
    if case == "npz_time_float":
        np.savez(npz, range=good.range, intrinsics=K, capture_time_ns=np.float64(1.5))
        return npz, {}
    if case == "npz_range_inf":
        r = good.range.copy()
        r[0, 0] = np.inf
        np.savez(npz, range=r, intrinsics=K)
        return npz, {}
    if case == "npz_huge_header":
        # The header claims 10^10 pixels and no data follows: refused before allocating.
        members = {"range.npy": _npy_header_only((100_000, 100_000)), "intrinsics.npy": _npy(K)}
        return _zip_with(npz, members), {}
    if case == "too_many_pixels":
        write_npz(good, npz)
        return npz, {"max_pixels": H * W - 1}
    png = tmp / "d.png"
    if case in ("png_no_intrinsics", "png_no_scale", "png_truncated", "png_rgb",
                "bad_scale_zero", "bad_scale_nan", "bad_scale_neg"):
        cv2.imwrite(str(png), np.full((H, W), 1000, np.uint16))
    if case == "png_no_intrinsics":
        return png, {"depth_scale": 0.001}
    if case == "png_no_scale":
        return png, {"intrinsics": INTR_S}
    if case == "png_truncated":
        png.write_bytes(png.read_bytes()[:60])
        return png, {"intrinsics": INTR_S, "depth_scale": 0.001}
    if case == "png_rgb":
        cv2.imwrite(str(png), np.zeros((H, W, 3), np.uint8))
        return png, {"intrinsics": INTR_S, "depth_scale": 0.001}
    if case == "png_huge_header":
        ihdr = struct.pack(">IIBBBBB", 100_000, 100_000, 16, 0, 0, 0, 0)
        png.write_bytes(b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr))
        return png, {"intrinsics": INTR_S, "depth_scale": 0.001}
    if case == "bad_scale_zero":
        return png, {"intrinsics": INTR_S, "depth_scale": 0.0}
    if case == "bad_scale_nan":
        return png, {"intrinsics": INTR_S, "depth_scale": float("nan")}
    if case == "bad_scale_neg":
        return png, {"intrinsics": INTR_S, "depth_scale": -0.001}
    if case == "tiff_truncated":
        tif = tmp / "d.tiff"
        cv2.imwrite(str(tif), np.ones((H, W), np.float32))
        tif.write_bytes(tif.read_bytes()[:200])
        return tif, {"intrinsics": INTR_S}
    if case.startswith("intrinsics_"):
        write_npz(good, npz)
        bad = {"intrinsics_short": "1,2,3", "intrinsics_text": "a,b,c,d",
               "intrinsics_nan": "nan,40,15,11", "intrinsics_zero": "0,40,15,11",
               "intrinsics_inf": "40,40,inf,11"}[case]
        return npz, {"intrinsics": bad}
    pcd = tmp / "c.pcd"
    if case == "pcd_unorganized":
        import open3d as o3d

        o3d.t.io.write_point_cloud(str(pcd), _o3d_cloud(good.points))
        return pcd, {}
    if case in ("pcd_truncated_binary", "pcd_truncated_compressed", "pcd_truncated_ascii"):
        write_pcd(pcd, good.points, ascii=case.endswith("ascii"),
                  compressed=case.endswith("compressed"))
        pcd.write_bytes(pcd.read_bytes()[: pcd.stat().st_size - 400])
        return pcd, {}
    if case == "pcd_garbage":
        pcd.write_bytes(b"\x00\x01garbage" * 50)
        return pcd, {}
    if case == "pcd_no_xyz":
        pcd.write_text("VERSION 0.7\nFIELDS a b\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\nWIDTH 2\n"
                       "HEIGHT 2\nPOINTS 4\nDATA ascii\n1 2\n1 2\n1 2\n1 2\n")
        return pcd, {}
    if case == "pcd_huge_header":
        pcd.write_text("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
                       "WIDTH 100000\nHEIGHT 100000\nPOINTS 10000000000\nDATA binary\n")
        return pcd, {}
    ply = tmp / "c.ply"
    if case == "ply_unorganized":
        import open3d as o3d

        o3d.t.io.write_point_cloud(str(ply), _o3d_cloud(good.points))
        return ply, {}
    if case == "ply_truncated":
        write_ply_o3d(ply, good.points)
        ply.write_bytes(ply.read_bytes()[:-500])
        return ply, {}
    if case == "ply_garbage":
        ply.write_bytes(b"garbage, not a ply\n")
        return ply, {}
    raise AssertionError(case)


BAD_CASES = {
    "missing": "not found",
    "directory": "got a directory",
    "suffix": "unsupported scan file type",
    "npz_garbage": "not a valid .npz",
    "npz_truncated": "not a valid .npz",
    "npz_corrupt_member": "corrupt",
    "npz_short_member": "corrupt or truncated",
    "npz_no_keys": "needs key 'range' or 'points'",
    "npz_range_3d": "'range' must be an \\(H, W\\) float array",
    "npz_range_int": "'range' must be an \\(H, W\\) float array",
    "npz_pickled": "'range' must be an \\(H, W\\) float array",
    "npz_points_shape": "'points' must be an \\(H, W, 3\\) float array",
    "npz_intrinsics_shape": "'intrinsics' must be a \\(3, 3\\)",
    "npz_intrinsics_nonfinite": "intrinsics must be finite",
    "npz_pose_shape": "'sensor_to_base' must be a \\(4, 4\\)",
    "npz_time_float": "'capture_time_ns' must be a 0-d integer",
    "npz_range_inf": "range must be finite or NaN",
    "npz_huge_header": "exceeds max_pixels",
    "too_many_pixels": "exceeds max_pixels",
    "png_no_intrinsics": "needs intrinsics",
    "png_no_scale": "needs --depth-scale",
    "png_truncated": "cannot decode image",
    "png_rgb": "must have one channel",
    "png_huge_header": "exceeds max_pixels",
    "bad_scale_zero": "depth scale must be finite and > 0",
    "bad_scale_nan": "depth scale must be finite and > 0",
    "bad_scale_neg": "depth scale must be finite and > 0",
    "tiff_truncated": "truncated TIFF|cannot decode image",
    "intrinsics_short": "FX,FY,CX,CY \\(four numbers\\)",
    "intrinsics_text": "FX,FY,CX,CY \\(four numbers\\)",
    "intrinsics_nan": "intrinsics must be finite",
    "intrinsics_inf": "intrinsics must be finite",
    "intrinsics_zero": "focal lengths must be positive",
    "pcd_unorganized": "unorganized",
    "pcd_truncated_binary": "truncated PCD",
    "pcd_truncated_compressed": "truncated PCD",
    "pcd_truncated_ascii": "truncated PCD",
    "pcd_garbage": "not a PCD file|malformed PCD header",
    "pcd_no_xyz": "no 'x' field",
    "pcd_huge_header": "exceeds max_pixels",
    "ply_unorganized": "unorganized",
    "ply_truncated": "truncated PLY",
    "ply_garbage": "not a PLY file",
}


@pytest.mark.parametrize("case", list(BAD_CASES))
def test_bad_input_raises_one_line(tmp_path: Path, case: str) -> None:
    path, kw = _case_files(tmp_path, case)
    with pytest.raises(InputError, match=BAD_CASES[case]) as ei:
        read_scan(path, **kw)  # type: ignore[arg-type]
    msg = str(ei.value)
    assert "\n" not in msg and len(msg) < 300, msg


def test_read_labels_needs_label_field(tmp_path: Path) -> None:
    write_pcd(tmp_path / "c.pcd", plane_scan().points, ascii=False, compressed=False)
    with pytest.raises(InputError, match="no 'label' field"):
        read_labels(tmp_path / "c.pcd")
    write_npz(plane_scan(), tmp_path / "s.npz")
    with pytest.raises(InputError, match="only be read from .pcd or .ply"):
        read_labels(tmp_path / "s.npz")


# --- the CLI on bad input ---------------------------------------------------------------

CLI_CASES = ["missing", "directory", "suffix", "npz_truncated", "png_no_intrinsics",
             "intrinsics_text", "bad_scale_zero", "pcd_unorganized", "npz_huge_header"]


def _cli_args(path: Path, kw: dict[str, object]) -> list[str]:
    args = [str(path)]
    if "intrinsics" in kw:
        args += ["--intrinsics", str(kw["intrinsics"])]
    if "depth_scale" in kw:
        args += ["--depth-scale", str(kw["depth_scale"])]
    return args


@pytest.mark.parametrize("case", CLI_CASES)
def test_cli_locate_bad_input_exits_2(tmp_path: Path, case: str) -> None:
    path, kw = _case_files(tmp_path, case)
    # one case in a real process (the exit code and stderr the shell sees), the others
    # through click's test runner: the same code path, without a Python start-up each
    if case == "npz_truncated":
        proc = subprocess.run(
            [sys.executable, "-m", "boxloc.cli", "locate", *_cli_args(path, kw)],
            capture_output=True, text=True, timeout=120,
        )
    else:
        proc = invoke("locate", *_cli_args(path, kw))
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("boxloc: error: ")
    assert "Traceback" not in proc.stderr
    assert proc.stdout == ""


# --- real data: mOSD ----------------------------------------------------------------------


@pytest.mark.real_data("learn0.pcd")
def test_mosd_learn0() -> None:
    scan = read_scan(MOSD / "learn0.pcd")
    labels = read_labels(MOSD / "learn0.pcd")
    assert scan.shape == (480, 640) and labels.shape == (480, 640)
    assert isinstance(scan.sensor, PinholeModel)
    assert scan.sensor.fx == pytest.approx(525.0, abs=0.01)
    assert scan.sensor.fy == pytest.approx(525.0, abs=0.01)
    assert scan.sensor.cx == pytest.approx(319.5, abs=0.01)
    assert scan.sensor.cy == pytest.approx(239.5, abs=0.01)
    nan = np.isnan(scan.range)
    # NaNs stay in place: label 0 marks exactly the points without a return.
    assert 0 < nan.mean() < 0.9
    assert np.array_equal(nan, labels == 0)
    assert set(np.unique(labels)) >= {0, 1}
    z = scan.points[..., 2][~nan]
    assert 0.3 < z.min() and z.max() < 3.0

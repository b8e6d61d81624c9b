"""ROS 2 bags in (boxloc.io.rosbag, run/import/replay) and results out (--publish-ros2).

Every bag here is written by ``rosbags`` itself (:func:`boxloc.io.rosbag.write_depth_bag`,
:class:`boxloc.io.rosbag.BagWriter`) from small simulated scans (160 x 120), in both storages.
"""

from __future__ import annotations

import dataclasses
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from cli_run import invoke
from replay_support import SPEC, product_differences

from boxloc.errors import InputError
from boxloc.io import range_from_depth, read_scan, read_scans
from boxloc.io.rosbag import (
    BagWriter,
    camera_info_message,
    depth_of,
    image_message,
    is_rosbag,
    open_bag,
    tf_message,
    write_depth_bag,
)
from boxloc.scan import PinholeModel, RayTableModel, Scan
from boxloc.simulate import simulate

PALLET = "pallet:width=160,height=120,f=131.25,distance=1.0"
T0 = 1_700_000_000_000_000_000


@pytest.fixture(scope="module")
def scans() -> list[Scan]:
    """Three simulated scans (a box, a pallet, a box) with their poses and capture times."""
    return [dataclasses.replace(simulate(spec, seed=s).scan, index=i)
            for i, (spec, s) in enumerate([(SPEC, 1), (PALLET, 2), (SPEC, 3)])]


def _stamps(n: int) -> list[int]:
    return [T0 + 123_456_789 + k * 100_000_000 for k in range(n)]


def _expected_range(raw: np.ndarray, scale: float, sensor: PinholeModel) -> np.ndarray:
    z = raw.astype(np.float64) * scale
    z[~(z > 0) | ~np.isfinite(z)] = np.nan
    return range_from_depth(z, sensor)


def _one_line_error(r: subprocess.CompletedProcess[str]) -> str:
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    return lines[0]


# --- reading -----------------------------------------------------------------------------


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("encoding,scale", [("16UC1", 0.001), ("32FC1", 1.0)])
def test_depth_images_read_bit_exact_with_stamp_and_source(
        tmp_path: Path, scans: list[Scan], storage: str, encoding: str, scale: float) -> None:
    stamps = _stamps(len(scans))
    bag = write_depth_bag(tmp_path / "bag", scans, storage=storage, encoding=encoding,
                          stamps_ns=stamps)
    assert is_rosbag(bag)
    got = list(read_scans(bag))
    assert [s.index for s in got] == [0, 1, 2]
    for k, (s, orig) in enumerate(zip(got, scans)):
        raw = depth_of(orig, encoding)
        assert s.sensor == orig.sensor  # K from CameraInfo
        # the recorded depth, scaled once, converted with the depth-image reader's helper
        assert s.range.tobytes() == _expected_range(raw, scale, orig.sensor).tobytes()
        assert s.capture_time_ns == stamps[k]
        assert s.source == str(bag)
        m = s.meta["rosbag"]
        assert (m["topic"], m["stamp_ns"], m["log_time_ns"]) == (
            "/camera/depth/image_raw", stamps[k], stamps[k])
        assert (m["encoding"], m["depth_scale"]) == (encoding, scale)
        assert m["info_topic"] == "/camera/depth/camera_info"
        assert m["info_stamp_ns"] == stamps[k]
    # the mm depth comes back exactly from the range: nothing was rounded on the way
    if encoding == "16UC1":
        stretch = range_from_depth(np.ones(scans[0].shape), scans[0].sensor)
        mm = np.rint(got[0].range / stretch.astype(np.float64) / 0.001)
        raw = depth_of(scans[0], encoding)
        ok = raw > 0
        assert np.array_equal(mm[ok], raw[ok]) and np.isnan(got[0].range[~ok]).all()


def test_a_bag_frame_and_the_same_frame_as_a_png_give_the_same_scan(
        tmp_path: Path, scans: list[Scan]) -> None:
    bag = write_depth_bag(tmp_path / "bag.mcap", scans[:1], single_file=True)
    raw = depth_of(scans[0], "16UC1")
    png = tmp_path / "depth.png"
    cv2.imwrite(str(png), raw)
    s = scans[0].sensor
    assert isinstance(s, PinholeModel)
    from_png = read_scan(png, intrinsics=(s.fx, s.fy, s.cx, s.cy), depth_scale=0.001)
    (from_bag,) = list(read_scans(bag))
    assert from_bag.range.tobytes() == from_png.range.tobytes()


def test_big_endian_and_padded_rows_read_as_recorded(tmp_path: Path, scans: list[Scan]
                                                     ) -> None:
    raw = depth_of(scans[0], "16UC1")
    H, W = raw.shape
    with BagWriter(tmp_path / "bag") as w:
        T = w.types
        w.write("/d/camera_info", camera_info_message(T, scans[0].sensor, T0, "cam"), T0)
        rows = np.zeros((H, W * 2 + 6), np.uint8)  # 6 bytes of padding per row
        rows[:, : W * 2] = raw.astype(">u2").view(np.uint8).reshape(H, W * 2)
        msg = image_message(T, raw, T0, "cam")
        msg.is_bigendian, msg.step, msg.data = 1, W * 2 + 6, rows.reshape(-1)
        w.write("/d/image_raw", msg, T0)
    (s,) = list(read_scans(tmp_path / "bag"))
    assert s.range.tobytes() == _expected_range(raw, 0.001, scans[0].sensor).tobytes()


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_an_organized_point_cloud(tmp_path: Path, scans: list[Scan], storage: str) -> None:
    bag = write_depth_bag(tmp_path / "bag", scans[:2], storage=storage, encoding="cloud",
                          stamps_ns=_stamps(2))
    got = list(read_scans(bag))
    assert len(got) == 2
    for s, orig in zip(got, scans):
        P = np.asarray(orig.points, np.float32)  # what the cloud holds
        ok = np.isfinite(P).all(-1)
        assert np.array_equal(s.valid, ok)
        np.testing.assert_allclose(s.points[ok], P[ok], rtol=2e-6, atol=1e-6)
        assert isinstance(s.sensor, PinholeModel)  # fitted to the organized points
        np.testing.assert_allclose([s.sensor.fx, s.sensor.cx], [131.25, 79.5], atol=1e-3)
        assert s.meta["rosbag"]["topic"] == "/camera/depth/points"
        assert s.sensor_to_base is not None


def test_an_unorganized_cloud_is_not_a_depth_topic(tmp_path: Path, scans: list[Scan]) -> None:
    flat = dataclasses.replace(scans[0])
    with BagWriter(tmp_path / "bag") as w:
        from boxloc.io.rosbag import cloud_message

        w.write("/points", cloud_message(w.types, flat.points.reshape(1, -1, 3), T0, "c"), T0)
    with pytest.raises(InputError, match="no depth Image .* or organized PointCloud2"):
        open_bag(tmp_path / "bag")
    with pytest.raises(InputError, match="not organized"):
        list(open_bag(tmp_path / "bag", depth_topic="/points"))


def _two_cameras(path: Path, scans: list[Scan], storage: str = "mcap") -> Path:
    """A bag with two depth cameras (/left 16UC1 of scans[0], /right 32FC1 of scans[1] with
    other intrinsics) and an RGB image topic, which is not depth."""
    right = scans[1].sensor
    assert isinstance(right, PinholeModel)
    right2 = dataclasses.replace(right, fx=140.0, fy=140.0)
    with BagWriter(path, storage=storage) as w:
        T = w.types
        for t in _stamps(2):
            w.write("/left/camera_info", camera_info_message(T, scans[0].sensor, t, "l"), t)
            w.write("/left/image_raw", image_message(T, depth_of(scans[0], "16UC1"), t, "l"), t)
            w.write("/right/camera_info", camera_info_message(T, right2, t, "r"), t)
            w.write("/right/image_raw", image_message(T, depth_of(scans[1], "32FC1"), t, "r"),
                    t)
            rgb = image_message(T, np.zeros((4, 4), np.uint16), t, "c")
            rgb.encoding, rgb.step, rgb.data = "rgb8", 12, np.zeros(48, np.uint8)
            w.write("/color/image_raw", rgb, t)
    return path


def test_several_depth_topics_are_named_and_one_is_chosen(tmp_path: Path, scans: list[Scan]
                                                          ) -> None:
    bag = _two_cameras(tmp_path / "bag", scans)
    r = invoke("import", str(bag), "--out", str(tmp_path / "x.mcap"))
    line = _one_line_error(r)
    assert "several depth topics (/left/image_raw, /right/image_raw)" in line
    assert "--depth-topic" in line and "/color" not in line
    assert not (tmp_path / "x.mcap").exists()
    got = list(read_scans(bag, depth_topic="/right/image_raw"))
    assert len(got) == 2
    s = got[0]
    assert isinstance(s.sensor, PinholeModel) and s.sensor.fx == 140.0  # its own CameraInfo
    assert s.meta["rosbag"]["info_topic"] == "/right/camera_info"
    assert s.range.tobytes() == _expected_range(depth_of(scans[1], "32FC1"), 1.0,
                                                s.sensor).tobytes()
    # a CameraInfo topic chosen by hand wins over the sibling
    (s2, _) = list(read_scans(bag, depth_topic="/right/image_raw",
                              info_topic="/left/camera_info"))
    assert s2.sensor == scans[0].sensor
    with pytest.raises(InputError, match="--depth-topic /nope: no Image or PointCloud2"):
        open_bag(bag, depth_topic="/nope")


def test_a_missing_camera_info_is_a_clear_error(tmp_path: Path, scans: list[Scan]) -> None:
    bag = write_depth_bag(tmp_path / "bag", scans[:1], camera_info=False)
    r = invoke("run", str(bag), "--quiet")
    line = _one_line_error(r)
    assert "no sensor_msgs/msg/CameraInfo topic" in line and "/camera/depth/image_raw" in line
    assert "--intrinsics" in line
    s0 = scans[0].sensor
    assert isinstance(s0, PinholeModel)
    (s,) = list(read_scans(bag, intrinsics=(s0.fx, s0.fy, s0.cx, s0.cy)))
    assert s.sensor == s0


def test_camera_info_matched_by_stamp_or_the_latest_before(tmp_path: Path,
                                                           scans: list[Scan]) -> None:
    s0 = scans[0].sensor
    assert isinstance(s0, PinholeModel)
    a, b = (dataclasses.replace(s0, fx=130.0), dataclasses.replace(s0, fx=133.0))
    t = _stamps(4)
    with BagWriter(tmp_path / "bag", storage="sqlite3") as w:
        T = w.types
        raw = depth_of(scans[0], "16UC1")
        # info b is recorded before the image of its stamp; info a an older one
        w.write("/c/camera_info", camera_info_message(T, a, t[0], "c"), t[0])
        w.write("/c/image_raw", image_message(T, raw, t[1], "c"), t[1])  # latest before: a
        w.write("/c/image_raw", image_message(T, raw, t[3], "c"), t[3] - 5)  # same stamp: b
        w.write("/c/camera_info", camera_info_message(T, b, t[3], "c"), t[3])
        w.write("/c/image_raw", image_message(T, raw, t[0] - 1, "c"), t[3] + 1)  # none before
    it = iter(open_bag(tmp_path / "bag"))
    first, second = next(it), next(it)
    assert isinstance(first.sensor, PinholeModel) and first.sensor.fx == 130.0
    assert isinstance(second.sensor, PinholeModel) and second.sensor.fx == 133.0
    with pytest.raises(InputError, match="1 frame.s. lost.*no CameraInfo .* at or before"):
        next(it)


def test_distortion(tmp_path: Path, scans: list[Scan]) -> None:
    """plumb_bob with coefficients gives each pixel's undistorted ray; another model with
    coefficients is refused in one line; any model with zero coefficients is a pinhole."""
    s0 = scans[0].sensor
    assert isinstance(s0, PinholeModel)
    d = (0.05, -0.02, 0.001, 0.0005, 0.0)
    raw = depth_of(scans[0], "16UC1")

    def bag(name: str, model: str, coeffs: Any) -> Path:
        with BagWriter(tmp_path / name) as w:
            T = w.types
            w.write("/c/camera_info", camera_info_message(T, s0, T0, "c", distortion_model=model,
                                                          d=coeffs), T0)
            w.write("/c/image_raw", image_message(T, raw, T0, "c"), T0)
        return tmp_path / name

    (s,) = list(read_scans(bag("pb", "plumb_bob", d)))
    assert isinstance(s.sensor, RayTableModel)
    u, v = 17, 101
    xy = cv2.undistortPoints(np.array([[[u, v]]], np.float64), s0.K, np.array(d)).reshape(2)
    ray = np.array([xy[0], xy[1], 1.0])
    np.testing.assert_allclose(s.sensor.table[v, u], ray / np.linalg.norm(ray), atol=1e-12)
    np.testing.assert_allclose(s.points[v, u, 2], raw[v, u] * 0.001, rtol=1e-6)  # z kept
    (p,) = list(read_scans(bag("eq0", "equidistant", (0.0,) * 4)))
    assert p.sensor == s0
    r = invoke("import", str(bag("rp", "rational_polynomial", (0.1,) + (0.0,) * 7)),
               "--out", str(tmp_path / "x.mcap"))
    line = _one_line_error(r)
    assert "distortion model 'rational_polynomial' with non-zero coefficients" in line


# --- the pose from /tf and /tf_static ----------------------------------------------------


def test_tf_static_gives_the_sensor_pose_and_up(tmp_path: Path, scans: list[Scan]) -> None:
    bag = write_depth_bag(tmp_path / "bag", scans[:1])
    assert "/tf_static" in open_bag(bag).bag.topics and "/tf" not in open_bag(bag).bag.topics
    (s,) = list(read_scans(bag))
    assert s.sensor_to_base is not None
    np.testing.assert_allclose(s.sensor_to_base, scans[0].sensor_to_base, atol=1e-12)
    np.testing.assert_allclose(s.up, scans[0].up, atol=1e-12)
    assert s.meta["rosbag"]["base_frame"] == "base_link"
    none = write_depth_bag(tmp_path / "none", scans[:1], tf=False)
    (n,) = list(read_scans(none))
    assert n.sensor_to_base is None


def _rot(axis: str, deg: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler(axis, deg, degrees=True).as_matrix()
    return T


def test_the_pose_follows_the_frame_chain_at_the_stamp(tmp_path: Path,
                                                       scans: list[Scan]) -> None:
    """world -> base_link (static) -> tool (moving, /tf) -> camera (static): the pose is
    the chain's product, the moving link interpolated at the image stamp."""
    world_base = _rot("z", 30.0)
    world_base[:3, 3] = (1.0, 2.0, 0.0)
    tool_cam = _rot("x", 180.0)
    tool_cam[:3, 3] = (0.0, 0.05, 0.1)
    a, b = _rot("y", 10.0), _rot("y", 30.0)
    a[:3, 3], b[:3, 3] = (0.5, 0.0, 1.5), (0.7, 0.2, 1.5)
    t = _stamps(3)
    raw = depth_of(scans[0], "16UC1")
    with BagWriter(tmp_path / "bag") as w:
        T = w.types
        w.write("/tf_static", tf_message(T, "world", "base_link", world_base, 0), t[0])
        w.write("/tf_static", tf_message(T, "/tool", "camera", tool_cam, 0), t[0])
        w.write("/tf", tf_message(T, "base_link", "tool", a, t[0]), t[0])
        w.write("/tf", tf_message(T, "base_link", "tool", b, t[2]), t[2])
        w.write("/c/camera_info", camera_info_message(T, scans[0].sensor, t[1], "camera"),
                t[1])
        w.write("/c/image_raw", image_message(T, raw, t[1], "camera"), t[1])
    (s,) = list(read_scans(tmp_path / "bag"))
    mid = _rot("y", 20.0)
    mid[:3, 3] = (0.6, 0.1, 1.5)
    assert s.meta["rosbag"]["base_frame"] == "world"
    np.testing.assert_allclose(s.sensor_to_base, world_base @ mid @ tool_cam, atol=1e-9)
    (sb,) = list(read_scans(tmp_path / "bag", base_frame="base_link"))
    np.testing.assert_allclose(sb.sensor_to_base, mid @ tool_cam, atol=1e-9)
    with pytest.raises(InputError, match="no transform from 'camera' to 'elsewhere'"):
        list(read_scans(tmp_path / "bag", base_frame="elsewhere"))


# --- damaged bags ------------------------------------------------------------------------


def _cut(bag: Path, frac: float, out: Path) -> Path:
    shutil.copytree(bag, out)
    (f,) = [q for q in out.iterdir() if q.suffix in (".mcap", ".db3")]
    data = f.read_bytes()
    f.write_bytes(data[: int(len(data) * frac)])
    return out


@pytest.mark.parametrize("storage,compress,encoding,n", [
    ("mcap", False, "16UC1", 10),
    # zstd chunks (1 MB uncompressed, 13 frames): the one cut short is lost, the others read
    ("mcap", True, "32FC1", 40),
    ("sqlite3", False, "16UC1", 10)])
def test_a_truncated_bag_gives_every_readable_frame_and_one_error(
        tmp_path: Path, scans: list[Scan], storage: str, compress: bool, encoding: str,
        n: int) -> None:
    many = [dataclasses.replace(scans[k % 3], index=k) for k in range(n)]
    full = write_depth_bag(tmp_path / "full", many, storage=storage, compress=compress,
                           encoding=encoding, stamps_ns=_stamps(n))
    whole = list(read_scans(full))
    cut = _cut(full, 0.6, tmp_path / "cut")
    got: list[Scan] = []
    with pytest.raises(InputError) as e:
        for s in read_scans(cut):
            got.append(s)
    msg = str(e.value)
    assert "\n" not in msg and "damaged bag" in msg and str(cut) in msg
    assert f"{len(got)} frame(s) of /camera/depth/image_raw read" in msg
    assert 3 <= len(got) < n  # the frames before the cut (the first 60 % of the file)
    for a, b in zip(got, whole):  # each one exactly as in the whole bag
        assert a.range.tobytes() == b.range.tobytes() and a.meta == {
            "rosbag": {**b.meta["rosbag"], "bag": str(cut)}}
    # `boxloc import` keeps them in a valid log and says what was lost, in one line
    r = invoke("import", str(cut), "--out", str(tmp_path / "cut.mcap"))
    assert "damaged bag" in _one_line_error(r)
    from recorder.mcap.log import open_log

    assert len(list(open_log(tmp_path / "cut.mcap").scans())) == len(got)


def test_a_corrupt_chunk_loses_only_its_frames(tmp_path: Path, scans: list[Scan]) -> None:
    """Three MCAP chunks (rosbags closes a chunk at 1 MB), given their CRCs as rosbag2's
    C++ writer does (rosbags writes none); bytes in the middle one overwritten: it fails its
    CRC and is lost, the frames of the others are read."""
    import zlib

    many = [dataclasses.replace(scans[k % 3], index=k) for k in range(30)]  # 77 kB each
    full = write_depth_bag(tmp_path / "full", many, encoding="32FC1", stamps_ns=_stamps(30))
    bad = shutil.copytree(full, tmp_path / "bad")
    (f,) = list(bad.glob("*.mcap"))
    data = bytearray(f.read_bytes())
    chunks, i = [], 8
    while i < len(data) and data[i] not in (0x02, 0x0F):  # the data section's records
        n = int.from_bytes(data[i + 1 : i + 9], "little")
        if data[i] == 0x06:
            body = i + 9
            assert data[body + 28 : body + 32] == b"\0\0\0\0"  # uncompressed
            records = body + 40
            crc = zlib.crc32(data[records : body + n])
            data[body + 24 : body + 28] = crc.to_bytes(4, "little")
            chunks.append((records, body + n))
        i += 9 + n
    assert len(chunks) >= 3
    start, end = chunks[1]
    mid = (start + end) // 2
    data[mid : mid + 64] = bytes(255 - x for x in data[mid : mid + 64])
    f.write_bytes(bytes(data))
    got: list[Scan] = []
    with pytest.raises(InputError, match="damaged bag.*(1 chunk.s. unreadable|checksum)"):
        for s in read_scans(bad):
            got.append(s)
    whole = {s.capture_time_ns: s.range.tobytes() for s in read_scans(full)}
    times = [s.capture_time_ns for s in got]
    stamps = _stamps(30)
    assert stamps[0] in times and stamps[-1] in times and len(got) < 30
    assert len(set(times)) == len(times)  # none twice (rosbags' part, then the records')
    assert all(whole[s.capture_time_ns] == s.range.tobytes() for s in got)


# --- run, record, replay, publish --------------------------------------------------------


def test_run_on_a_bag_records_its_provenance_and_replays_with_zero_diff(
        tmp_path: Path, scans: list[Scan]) -> None:
    stamps = _stamps(2)
    bag = write_depth_bag(tmp_path / "bag.mcap", scans[:2], single_file=True, stamps_ns=stamps)
    log = tmp_path / "run.mcap"
    r = invoke("run", str(bag), "--record", str(log), "--quiet")
    assert r.returncode == 0, r.stderr
    from recorder.mcap.log import open_log

    recorded = [x.scan for x in open_log(log).scans()]
    assert [s.capture_time_ns for s in recorded] == stamps
    for k, s in enumerate(recorded):
        m = s.meta["rosbag"]
        assert s.source == str(bag) and m["bag"] == str(bag)
        assert (m["topic"], m["stamp_ns"], m["log_time_ns"]) == (
            "/camera/depth/image_raw", stamps[k], stamps[k])
        # each scan's own pose, from /tf at its stamp (the two poses differ)
        assert s.sensor_to_base is not None
        np.testing.assert_allclose(s.sensor_to_base, scans[k].sensor_to_base, atol=1e-12)
    r = invoke("replay", str(log), "--out", str(tmp_path / "rep"), "-j", "1", "--quiet")
    assert r.returncode == 0, r.stderr
    assert product_differences(log, tmp_path / "rep" / "run.mcap") == []
    # `boxloc diff` agrees
    assert invoke("diff", str(log), str(tmp_path / "rep" / "run.mcap")).returncode == 0


def test_replay_and_import_take_a_bag_directly(tmp_path: Path, scans: list[Scan]) -> None:
    bag = write_depth_bag(tmp_path / "bag", scans[:2], storage="sqlite3")
    r = invoke("replay", str(bag), "--out", str(tmp_path / "rep"), "-j", "1", "--quiet")
    assert r.returncode == 0, r.stderr
    assert "not diffed" in r.stderr
    r = invoke("import", str(bag), "--out", str(tmp_path / "imp.mcap"))
    assert r.returncode == 0, r.stderr
    from recorder.mcap.log import open_log

    direct = list(read_scans(bag))
    for path in (tmp_path / "rep" / "bag.mcap", tmp_path / "imp.mcap"):
        back = [x.scan for x in open_log(path).scans()]
        assert [s.range.tobytes() for s in back] == [s.range.tobytes() for s in direct]
        assert [s.meta for s in back] == [s.meta for s in direct]


def test_publish_ros2_writes_poses_and_markers_standard_tools_read(
        tmp_path: Path, scans: list[Scan]) -> None:
    stamps = _stamps(2)
    bag = write_depth_bag(tmp_path / "bag", scans[:2], stamps_ns=stamps)
    out, log = tmp_path / "surfaces.mcap", tmp_path / "run.mcap"
    r = invoke("run", str(bag), "--record", str(log), "--publish-ros2", str(out), "--quiet")
    assert r.returncode == 0, r.stderr
    from recorder.mcap.log import open_log

    results = [(x.scan, x.products["surfaces"]) for x in open_log(log).scans()]
    assert sum(len(s.width) for _, s in results) > 0

    # rosbags reads it back as a ROS 2 bag
    from rosbags.highlevel import AnyReader

    with AnyReader([out]) as rd:
        assert {c.topic: c.msgtype for c in rd.connections} == {
            "/boxloc/grasp_poses": "geometry_msgs/msg/PoseArray",
            "/boxloc/surfaces": "visualization_msgs/msg/MarkerArray",
            "/boxloc/ambiguous": "visualization_msgs/msg/MarkerArray"}
        msgs = [(c.topic, t, rd.deserialize(raw, c.msgtype)) for c, t, raw in rd.messages()]
    poses = [m for topic, _, m in msgs if topic == "/boxloc/grasp_poses"]
    marks = [m for topic, _, m in msgs if topic == "/boxloc/surfaces"]
    assert [t for topic, t, _ in msgs if topic == "/boxloc/grasp_poses"] == stamps
    for pa, ma, (_, surf), t in zip(poses, marks, results, stamps):
        assert pa.header.frame_id == "camera_depth_optical_frame"
        assert pa.header.stamp.sec * 10**9 + pa.header.stamp.nanosec == t
        order = np.argsort(surf.pick_order, kind="stable")
        got = np.array([[p.position.x, p.position.y, p.position.z] for p in pa.poses])
        np.testing.assert_array_equal(got.reshape(-1, 3), surf.grasp_points[order])
        for p, k in zip(pa.poses, order):  # orientation: z the normal, x the width axis
            from scipy.spatial.transform import Rotation

            q = p.orientation
            R = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
            np.testing.assert_allclose(R[:, 2], surf.normals[k], atol=1e-9)
            assert abs(R[:, 0] @ surf.x_axis[k]) > 0.999
        assert ma.markers[0].action == 3  # DELETEALL
        lines = [m for m in ma.markers if m.ns == "boxloc/rectangles"]
        assert len(lines) == len(surf.width)
        for m, k in zip(lines, order):
            ring = np.array([[q.x, q.y, q.z] for q in m.points])
            np.testing.assert_array_equal(ring, np.vstack([surf.corners[k], surf.corners[k][:1]]))
    # an independent CDR decoder (mcap-ros2-support-fast) and pymcap-cli's doctor accept it
    from mcap.reader import make_reader
    from mcap_ros2_support_fast.decoder import DecoderFactory

    with open(out, "rb") as f:
        rd2 = make_reader(f, decoder_factories=[DecoderFactory()])
        n = sum(1 for _ in rd2.iter_decoded_messages())
        assert rd2.get_header().profile == "ros2"
    assert n == 6  # poses, rectangles and ambiguous regions of two scans
    doctor = shutil.which("pymcap-cli", path=str(Path(sys.executable).parent)) or "pymcap-cli"
    d = subprocess.run([doctor, "doctor", str(out)], capture_output=True, text=True, timeout=120)
    assert d.returncode == 0, d.stdout + d.stderr
    # never over an existing file without --force
    r = invoke("run", str(bag), "--publish-ros2", str(out), "--quiet")
    assert "exists" in _one_line_error(r)


def test_a_boxloc_log_is_not_a_bag_and_bags_cost_nothing_at_start_up(tmp_path: Path,
                                                                    scans: list[Scan]) -> None:
    from boxloc.io import write_npz

    write_npz(scans[0], tmp_path / "s.npz")
    log = tmp_path / "log.mcap"
    assert invoke("import", str(tmp_path / "s.npz"), "--out", str(log)).returncode == 0
    assert not is_rosbag(log) and not is_rosbag(tmp_path / "s.npz")
    assert is_rosbag(write_depth_bag(tmp_path / "b.db3", scans[:1], storage="sqlite3",
                                     single_file=True))
    code = ("import sys; import boxloc.cli, boxloc.io, recorder.commands, recorder.import_cmd, "
            "replay.commands; from boxloc.io import read_scans; "
            f"list(read_scans({str(tmp_path / 's.npz')!r})); "
            "print(sorted(m for m in sys.modules if m.startswith('rosbags')))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "[]"


def test_the_sample_bag_in_logs(tmp_path: Path) -> None:
    """logs/ros2-pallet-320x240: the two pallet scans of logs/pallet-320x240.mcap, as a
    camera records them, within the sample budget (1.5 MB)."""
    bag = Path(__file__).resolve().parent.parent / "logs" / "ros2-pallet-320x240"
    assert is_rosbag(bag)
    assert sum(f.stat().st_size for f in bag.iterdir()) <= 1_500_000
    got = list(read_scans(bag))
    assert [s.shape for s in got] == [(240, 320)] * 2
    for k, s in enumerate(got):
        sim = simulate("pallet:width=320,height=240,f=262.5", seed=k + 1).scan
        assert s.sensor == sim.sensor and s.capture_time_ns == sim.capture_time_ns
        assert s.sensor_to_base is not None
        np.testing.assert_allclose(s.sensor_to_base, sim.sensor_to_base, atol=1e-12)
        assert s.range.tobytes() == _expected_range(depth_of(sim, "16UC1"), 0.001,
                                                    sim.sensor).tobytes()

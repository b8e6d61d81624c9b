"""The ``bag`` cases: ROS 2 bags with mutated bytes, or valid bags with hostile messages.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from recorder.fuzz.cases import Job, Step, _pick
from recorder.fuzz.mutate import mutate_bytes
from recorder.fuzz.scan_files import _roundtrip, _storm


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

"""The corpus: valid inputs to mutate (small logs, scan files of every format, bags),
written once per run.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from boxloc.errors import BoxlocError
from recorder.fuzz.cloud_files import pcd_bytes, ply_bytes


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


#: The file in a corpus directory that lists its inputs (what :func:`build_corpus` returned).
CORPUS_INDEX = "corpus.json"


def corpus_at(d: Path, sample_logs: Sequence[str | os.PathLike[str]] = ()) -> dict[str, Any]:
    """The corpus in ``d``: the one written there before (listed in ``d/corpus.json``),
    else a new one (written, then listed).

    Two builds never agree byte for byte (the corpus logs hold the stages' wall-clock
    timings and their creation time), so runs that must be given the same inputs, such as
    a comparison of two runs' cases, share one corpus directory.

    Raises
    ------
    InputError
        ``d/corpus.json`` is not a corpus index, or names a file that is gone.
    """
    from boxloc.errors import InputError

    index = d / CORPUS_INDEX
    if not index.is_file():
        corpus = build_corpus(d, sample_logs)
        index.write_text(json.dumps(corpus, indent=1) + "\n")
        return corpus
    try:
        corpus = json.loads(index.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise InputError(f"{index} is not a fuzz corpus index: {e}") from None
    if not isinstance(corpus, dict) or not isinstance(corpus.get("small_logs"), list):
        raise InputError(f"{index} is not a fuzz corpus index (no small_logs list)")
    files = [f for v in corpus.values() if isinstance(v, list) for f in v]
    for f in [*files, corpus.get("sidecar", "")]:  # the other entries are not paths
        if not Path(str(f)).is_file():
                raise InputError(f"{index} names {f}, which is not a file")
    return corpus

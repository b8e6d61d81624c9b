"""The public readers: :func:`read_scan` (one file, the format chosen by its suffix),
:func:`read_scans` (a file, a directory or a ROS 2 bag) and :func:`read_labels`.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from boxloc.errors import InputError
from boxloc.io.cloud import _read_cloud, _scan_from_cloud
from boxloc.io.common import (
    DEFAULT_MAX_PIXELS,
    SUPPORTED_SUFFIXES,
    IntrinsicsLike,
    PathLike,
    _check_depth_scale,
    _check_path,
    _one_line,
    parse_intrinsics,
)
from boxloc.io.depth_image import _read_depth_image
from boxloc.io.npz import _read_npz
from boxloc.scan import Scan


def read_scan(
    path: PathLike,
    *,
    intrinsics: IntrinsicsLike = None,
    depth_scale: float | None = None,
    index: int = 0,
    max_pixels: int = DEFAULT_MAX_PIXELS,
) -> Scan:
    """Read one scan from a ``.npz``, depth PNG/TIFF, or organized PCD/PLY file.

    Parameters
    ----------
    path : str or Path
        The file; the format is chosen by its suffix (see ``SUPPORTED_SUFFIXES``).
    intrinsics : str, sequence of 4 floats or ndarray (3, 3), optional
        Pinhole ``fx, fy, cx, cy`` in pixels (the ``--intrinsics`` option). Required for depth
        images and for an ``.npz`` with ``range`` but no ``intrinsics``. For a point cloud it
        sets the pinhole model instead of fitting one. It must agree with intrinsics stored in
        an ``.npz``.
    depth_scale : float, optional
        Metres per depth unit for PNG/TIFF depth images (0.001 for millimetres). Required for
        integer images; float images default to 1.0 (metres). Checked, but not used, for
        other formats (so one option set can serve a directory of mixed files).
    index : int
        Sequence number stored in ``Scan.index``.
    max_pixels : int
        Largest scan accepted, pixels; the size is checked from the file header before the
        data are loaded whenever the format allows.

    Returns
    -------
    Scan
        ``range`` (H, W) float32 metres, NaN for no return, with a pinhole or ray-table sensor.

    Raises
    ------
    InputError
        Missing file, directory, unknown suffix, unreadable, truncated or corrupt file, wrong
        shape or dtype, missing or invalid intrinsics, invalid depth scale, organization
        missing, or a scan larger than ``max_pixels``.
    """
    p = _check_path(path)
    intr = parse_intrinsics(intrinsics)
    scale = _check_depth_scale(depth_scale)
    if not isinstance(max_pixels, int) or max_pixels <= 0:
        raise InputError(f"max_pixels must be a positive integer, got {max_pixels!r}")
    suffix = p.suffix.lower()
    try:
        if suffix == ".npz":
            scan = _read_npz(p, intr, max_pixels, index)
        elif suffix in (".png", ".tif", ".tiff"):
            scan = _read_depth_image(p, intr, scale, max_pixels, index)
        else:
            cloud = _read_cloud(p, max_pixels, want_labels=False)
            scan = _scan_from_cloud(p, cloud, intr, index)
    except InputError:
        raise
    except MemoryError:
        raise InputError(f"{p}: not enough memory to read this scan") from None
    except OSError as e:
        raise InputError(f"cannot read {p}: {e.strerror or _one_line(e)}") from None
    return scan


def read_scans(path_or_dir: PathLike, **same: Any) -> Iterator[Scan]:
    """Read one scan file, or every supported file in a directory sorted by name, or the
    depth frames of a ROS 2 bag (:func:`boxloc.io.rosbag.open_bag`).

    Parameters
    ----------
    path_or_dir : str or Path
        A scan file, or a directory of them (not recursive; other files are skipped), or a
        ROS 2 bag (a rosbag2 directory, an ``.mcap`` file of profile ``ros2``, a ``.db3``).
    **same
        Keyword arguments of :func:`read_scan`, the same for every file. In a directory
        ``index`` counts from its value (default 0) in name order. ``depth_topic``,
        ``info_topic`` and ``base_frame`` are for bags (ignored for other inputs).

    Yields
    ------
    Scan

    Raises
    ------
    InputError
        As :func:`read_scan`; also for a directory without any scan file.
    """
    p = Path(path_or_dir)
    # ROS 2 bags (boxloc.io.rosbag, its reader imported only for a bag): their own options.
    bag_kw: dict[str, Any] = {k: same.pop(k) for k in ("depth_topic", "info_topic",
                                                        "base_frame") if k in same}
    from boxloc.io.rosbag import is_rosbag

    if is_rosbag(p):
        yield from _read_bag(p, bag_kw, same)
        return
    if not p.is_dir():
        yield read_scan(p, **same)
        return
    files = sorted(f for f in p.iterdir()
                   if f.is_file() and f.suffix.lower() in SUPPORTED_SUFFIXES)
    if not files:
        raise InputError(f"no scan files ({', '.join(SUPPORTED_SUFFIXES)}) in directory {p}")
    start = int(same.pop("index", 0))
    for i, f in enumerate(files):
        yield read_scan(f, index=start + i, **same)


def _read_bag(p: Path, bag_kw: dict[str, Any], same: dict[str, Any]) -> Iterator[Scan]:
    from boxloc.io.rosbag import open_bag

    yield from open_bag(p, **bag_kw, **same)


def read_labels(path: PathLike, *, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Read the ``label`` field of an organized PCD (or PLY) as an image.

    Parameters
    ----------
    path : str or Path
        A PCD/PLY file with an integer ``label`` field, e.g. an mOSD frame (0 = no return,
        1-9 = table, 10*k + j = part j of object k).
    max_pixels : int
        Largest cloud accepted, pixels.

    Returns
    -------
    ndarray, shape (H, W), int64
        The label of each pixel, in the same layout as :func:`read_scan`'s range.

    Raises
    ------
    InputError
        As :func:`read_scan`, or when the file has no ``label`` field.
    """
    p = _check_path(path)
    if p.suffix.lower() not in (".pcd", ".ply"):
        raise InputError(f"labels can only be read from .pcd or .ply files, got {p}")
    try:
        cloud = _read_cloud(p, max_pixels, want_labels=True)
    except OSError as e:
        raise InputError(f"cannot read {p}: {e.strerror or _one_line(e)}") from None
    assert cloud.labels is not None
    return cloud.labels

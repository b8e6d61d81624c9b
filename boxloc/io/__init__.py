"""Scan files in, ``.npz`` out: one module per format, and ROS 2 bags.

Every reader returns a :class:`boxloc.scan.Scan`. Every problem with the user's file raises
:class:`boxloc.errors.InputError` with one line that names the file and the problem; library
exceptions (zip, zlib, OpenCV, Open3D) never escape. An all-NaN scan is accepted by the
readers (it is a valid recording of nothing); the pipeline's ``check_scan`` refuses it.

Modules
-------
:mod:`~boxloc.io.read`
    :func:`read_scan`, :func:`read_scans`, :func:`read_labels`: the format is chosen by the
    file's suffix (``SUPPORTED_SUFFIXES``); a directory or a ROS 2 bag gives many scans.
:mod:`~boxloc.io.npz`
    The public, stable ``.npz`` layout (see :func:`write_npz`), read and written.
:mod:`~boxloc.io.depth_image`
    16-bit PNG, 8/16-bit or float TIFF depth images (*z* depth, not range).
:mod:`~boxloc.io.cloud`, :mod:`~boxloc.io.pcd`, :mod:`~boxloc.io.ply`
    Organized PCD (ascii, binary, binary_compressed) and PLY clouds: decoded by Open3D, the
    organization from our own header parse.
:mod:`~boxloc.io.common`
    The checks every reader shares (path, size, intrinsics, depth scale).
:mod:`~boxloc.io.rosbag`
    Depth frames of ROS 2 bags, and small bags written for tests and samples (imported on
    first use only).
"""

from __future__ import annotations

from boxloc.io.common import DEFAULT_MAX_PIXELS, SUPPORTED_SUFFIXES, parse_intrinsics
from boxloc.io.depth_image import range_from_depth
from boxloc.io.npz import write_arrays_npz, write_npz
from boxloc.io.read import read_labels, read_scan, read_scans

__all__ = [
    "SUPPORTED_SUFFIXES",
    "DEFAULT_MAX_PIXELS",
    "parse_intrinsics",
    "read_scan",
    "read_scans",
    "read_labels",
    "write_npz",
    "write_arrays_npz",
    "range_from_depth",
]

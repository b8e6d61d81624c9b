"""Which files are ROS 2 bags: a rosbag2 directory, a ``.db3`` file, or an ``.mcap`` file of
profile ``ros2`` (boxloc's own MCAP logs have none).
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

_MCAP_MAGIC = b"\x89MCAP0\r\n"


PathLike = str | os.PathLike[str]


def _mcap_profile(p: Path) -> str | None:
    """The profile of an MCAP file's header record, or None when it is not MCAP."""
    try:
        with open(p, "rb") as f:
            head = f.read(8 + 1 + 8 + 4 + 64)
    except OSError:
        return None
    if len(head) < 21 or head[:8] != _MCAP_MAGIC or head[8] != 0x01:
        return None
    (n,) = struct.unpack_from("<I", head, 17)
    return head[21 : 21 + n].decode("utf-8", "replace") if n <= 64 else None


def is_rosbag(path: PathLike) -> bool:
    """Whether ``path`` is a ROS 2 bag: a directory with ``metadata.yaml``, a ``.db3`` file,
    or an ``.mcap`` file whose header profile is ``ros2`` (boxloc's logs have none)."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").is_file()
    if not p.is_file():
        return False
    suffix = p.suffix.lower()
    if suffix == ".db3":
        return True
    return suffix == ".mcap" and _mcap_profile(p) == "ros2"

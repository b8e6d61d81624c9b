"""Write ``ros2-pallet-320x240/``: a ROS 2 bag of the two pallet scans of
``pallet-320x240.mcap`` (seeds 1 and 2), as a depth camera driver records them.

A rosbag2 directory (MCAP storage, zstd chunks): ``/camera/depth/image_raw`` 16UC1
millimetres with ``/camera/depth/camera_info`` on the same stamps, and the camera's pose on
``/tf`` at each stamp (``base_link`` -> ``camera_depth_optical_frame``; the simulator moves
the camera a little between scans). Written by rosbags
(:func:`boxloc.io.rosbag.write_depth_bag`); the same rosbags version writes the same bytes.
Run by ``make-samples.sh``, or from the repository root: ``python logs/make-ros2-sample.py``.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

from boxloc.io.rosbag import write_depth_bag
from boxloc.simulate import simulate

OUT = Path(__file__).resolve().parent / "ros2-pallet-320x240"


def main() -> None:
    shutil.rmtree(OUT, ignore_errors=True)
    scans = [dataclasses.replace(simulate("pallet:width=320,height=240,f=262.5",
                                          seed=seed).scan, index=i)
             for i, seed in enumerate((1, 2))]
    write_depth_bag(OUT, scans, compress=True)
    size = sum(f.stat().st_size for f in OUT.iterdir())
    print(f"{OUT.name}: {len(scans)} scans, {size} bytes")


if __name__ == "__main__":
    main()

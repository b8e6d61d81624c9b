"""``--publish-ros2``: the ambiguous regions (issue #21) beside the surfaces, read back.

The scene is the packed-layer one of ``tests/test_packed.py``: two touching 0.3 x 0.4 m
cartons of equal height with sharp edges and no gap. Without a carton list their union is
one ambiguous region and no surface; with the list it is two surfaces and no region. Both
runs go through ``boxloc run --publish-ros2`` and the bag is read back with rosbags.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cli_run import invoke
from scenes import box, scene

from boxloc.io import write_npz
from boxloc.products import AmbiguityReason
from recorder.mcap.log import open_log
from recorder.mcap.ros2_publish import (
    AMBIGUOUS_NS,
    AMBIGUOUS_REASON_NS,
    AMBIGUOUS_TOPIC,
    GRASP_TOPIC,
    MARKER_TOPIC,
)

#: the site's carton range (tests/test_packed.py): two cartons side by side exceed max_edge
SITE = ("--set", "min_edge=0.15", "--set", "max_edge=0.5")
TWO = [box(-0.15, 0.0, 0.3, 0.4, 0.25), box(0.15, 0.0, 0.3, 0.4, 0.25)]
_LINE_STRIP, _TEXT, _DELETEALL = 4, 9, 3


@pytest.fixture(scope="module")
def two(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The two-carton scan as an .npz (exact points, no depth quantization)."""
    path = tmp_path_factory.mktemp("two") / "two.npz"
    write_npz(scene(TWO, distance=1.5, tilt=0.08, bevel=0.0).scan, path)
    return path


def _read_bag(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """Every message of a ROS 2 bag by topic: (log time ns, message), with rosbags."""
    from rosbags.highlevel import AnyReader

    out: dict[str, list[tuple[int, Any]]] = {}
    with AnyReader([path]) as rd:
        types = {c.topic: c.msgtype for c in rd.connections}
        assert types == {GRASP_TOPIC: "geometry_msgs/msg/PoseArray",
                         MARKER_TOPIC: "visualization_msgs/msg/MarkerArray",
                         AMBIGUOUS_TOPIC: "visualization_msgs/msg/MarkerArray"}
        for c, t, raw in rd.messages():
            out.setdefault(c.topic, []).append((t, rd.deserialize(raw, c.msgtype)))
    return out


def _run(scan: Path, out: Path, log: Path, *extra: str) -> tuple[Any, dict[str, Any]]:
    r = invoke("run", str(scan), *SITE, *extra, "--record", str(log), "--publish-ros2",
               str(out), "--quiet")
    assert r.returncode == 0, r.stderr
    (rec,) = list(open_log(log).scans())
    return rec, _read_bag(out)


def test_an_ambiguous_region_is_published_with_its_outline_and_reason(two: Path,
                                                                      tmp_path: Path) -> None:
    rec, bag = _run(two, tmp_path / "out.mcap", tmp_path / "run.mcap")
    A = rec.products["ambiguous"]
    assert len(A) == 1 and len(rec.products["surfaces"].width) == 0  # the scene's premise
    (t_pose, poses), = bag[GRASP_TOPIC]
    (t_amb, amb), = bag[AMBIGUOUS_TOPIC]
    assert poses.poses == [] and t_amb == t_pose  # no pick; the same stamp as the poses
    assert amb.markers[0].action == _DELETEALL  # the previous scan's regions go
    lines = [m for m in amb.markers if m.ns == AMBIGUOUS_NS]
    texts = [m for m in amb.markers if m.ns == AMBIGUOUS_REASON_NS]
    assert len(lines) == len(texts) == 1
    (line,), (text,) = lines, texts
    assert line.type == _LINE_STRIP and line.id == 0 and line.header.frame_id == "sensor"
    assert line.header.stamp.sec * 10**9 + line.header.stamp.nanosec == t_amb
    ring = np.array([[q.x, q.y, q.z] for q in line.points])
    np.testing.assert_array_equal(ring, np.vstack([A.corners[0], A.corners[0][:1]]))
    assert text.type == _TEXT and text.id == 0
    assert text.text == AmbiguityReason(int(A.reason[0])).name.lower() == "larger_than_max_box"
    c = text.pose.position
    np.testing.assert_allclose([c.x, c.y, c.z], A.corners[0].mean(axis=0), atol=1e-12)
    # the surfaces' markers hold only their DELETEALL: the region is not a surface
    ((_, surf),) = bag[MARKER_TOPIC]
    assert [m.action for m in surf.markers] == [_DELETEALL]


def test_with_the_carton_list_the_region_is_split_and_none_is_published(
        two: Path, tmp_path: Path) -> None:
    sizes = tmp_path / "sizes.csv"
    sizes.write_text("width,length,height\n0.4,0.3,0.25\n")
    rec, bag = _run(two, tmp_path / "out.mcap", tmp_path / "run.mcap",
                    "--box-sizes", str(sizes))
    assert len(rec.products["ambiguous"]) == 0 and len(rec.products["surfaces"].width) == 2
    ((_, poses),) = bag[GRASP_TOPIC]
    ((_, amb),) = bag[AMBIGUOUS_TOPIC]
    assert len(poses.poses) == 2
    assert [m.action for m in amb.markers] == [_DELETEALL]  # nothing ambiguous left

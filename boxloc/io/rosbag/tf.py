"""The ``/tf_static`` and ``/tf`` transform tree of a bag: the sensor pose at a stamp.

Dynamic transforms are interpolated between the samples around the stamp (slerp and lerp),
never extrapolated.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from boxloc.errors import InputError
from boxloc.io.rosbag.decode import _frame, _stamp_ns

#: Longest chain of frames followed in /tf (a robot arm has tens; a cycle is damage).
_MAX_TF_DEPTH = 64


def _transform(tr: Any) -> np.ndarray:
    """4x4 parent_from_child of a geometry_msgs/Transform; ValueError if not a rotation."""
    from scipy.spatial.transform import Rotation

    q = tr.rotation
    t = tr.translation
    v = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    xyz = np.array([t.x, t.y, t.z], dtype=np.float64)
    if not (np.isfinite(v).all() and np.isfinite(xyz).all()) or np.linalg.norm(v) < 1e-9:
        raise ValueError("transform is not finite or its quaternion is zero")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(v).as_matrix()
    T[:3, 3] = xyz
    return T


def _interpolate(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
    """The transform a fraction ``w`` of the way from ``a`` to ``b`` (slerp, lerp)."""
    from scipy.spatial.transform import Rotation, Slerp

    s = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]])))
    T = np.eye(4)
    T[:3, :3] = s([w]).as_matrix()[0]
    T[:3, 3] = (1 - w) * a[:3, 3] + w * b[:3, 3]
    return T


@dataclass
class TfTree:
    """The transforms of a bag's ``/tf_static`` and ``/tf``: parent and 4x4 parent_from_child
    per child frame (static), or time-stamped samples (dynamic)."""

    static: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)
    dynamic: dict[str, tuple[str, list[tuple[int, np.ndarray]]]] = field(default_factory=dict)

    def add(self, msg: Any, static: bool) -> None:
        for ts in msg.transforms:
            child, parent = _frame(ts.child_frame_id), _frame(ts.header.frame_id)
            if not child or not parent or child == parent:
                continue
            try:
                T = _transform(ts.transform)
            except ValueError:
                continue
            if static:
                self.static[child] = (parent, T)
            else:
                _, samples = self.dynamic.setdefault(child, (parent, []))
                samples.append((_stamp_ns(ts.header), T))

    def __bool__(self) -> bool:
        return bool(self.static or self.dynamic)

    def _edge(self, child: str, t_ns: int) -> tuple[str, np.ndarray] | None:
        if child in self.static:
            return self.static[child]
        if child not in self.dynamic:
            return None
        parent, samples = self.dynamic[child]
        samples.sort(key=lambda s: s[0])
        times = [s[0] for s in samples]
        k = int(np.searchsorted(times, t_ns, side="right"))
        if k == 0:
            return None  # every sample is after the stamp: no extrapolation
        t0, a = samples[k - 1]
        if t0 == t_ns or k == len(samples):
            return parent, a
        t1, b = samples[k]
        return parent, _interpolate(a, b, (t_ns - t0) / (t1 - t0))

    def chain(self, frame: str, t_ns: int) -> tuple[str, np.ndarray]:
        """The root reached from ``frame`` at ``t_ns`` and root_from_frame (4x4)."""
        T = np.eye(4)
        f = frame
        for _ in range(_MAX_TF_DEPTH):
            e = self._edge(f, t_ns)
            if e is None:
                return f, T
            f, T = e[0], e[1] @ T
        raise InputError(f"/tf: the frame chain from {frame!r} is longer than "
                         f"{_MAX_TF_DEPTH} links (a cycle?)")

    def lookup(self, base: str | None, frame: str, t_ns: int) -> tuple[str, np.ndarray] | None:
        """``(base, base_from_frame)`` at ``t_ns``; ``base`` None: the root of ``frame``'s
        tree. None when the frames are not connected at that time."""
        root, root_from_frame = self.chain(frame, t_ns)
        if base is None:
            return None if root == frame else (root, root_from_frame)
        broot, root_from_base = self.chain(base, t_ns)
        if broot != root:
            return None
        return base, np.linalg.inv(root_from_base) @ root_from_frame

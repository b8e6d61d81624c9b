"""Constructed scenes with known answers for the stage tests (from the simulator's own API)."""

from __future__ import annotations

import numpy as np

from boxloc.simulate import PALLET_SIZE, SceneSpec, SimulatedScan, look_down_pose, simulate_boxes

TOP = PALLET_SIZE[2]


def box(x: float, y: float, sx: float, sy: float, sz: float, yaw: float = 0.0) -> list[float]:
    """A box standing on the pallet, base frame: centre x, y, z, size x, y, z, yaw."""
    return [x, y, TOP + sz / 2, sx, sy, sz, yaw]


def scene(
    boxes: list[list[float]],
    distance: float = 1.5,
    tilt: float = 0.08,
    seed: int = 1,
    **spec: object,
) -> SimulatedScan:
    """Render boxes from ``distance`` above the highest top, slightly tilted."""
    b = np.array(boxes, dtype=np.float64).reshape(-1, 7)
    top = float((b[:, 2] + b[:, 5] / 2).max()) if len(b) else TOP
    T = look_down_pose([0.0, 0.0, top], distance, tilt=tilt, azimuth=0.7, roll=0.3)
    return simulate_boxes(b, T, spec=SceneSpec(kind="single", **spec), seed=seed)  # type: ignore[arg-type]


def wall(distance: float = 1.5) -> np.ndarray:
    """A flat wall ``distance`` ahead seen by a 64 x 48 pinhole: (48, 64, 3) points, no edges."""
    v, u = np.mgrid[0:48, 0:64].astype(np.float64)
    z = np.full_like(u, distance)
    return np.stack([(u - 31.5) / 50 * z, (v - 23.5) / 50 * z, z], -1)

"""The sensor pose: a camera looking down at the pile, drawn from the scene's pose stream."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from boxloc.simulate.boxes import _PALLET_TOP, _footprint_corners
from boxloc.simulate.spec import SceneSpec

__all__ = ["look_down_pose"]


def look_down_pose(
    target: npt.ArrayLike, distance: float, tilt: float = 0.0, azimuth: float = 0.0,
    roll: float = 0.0,
) -> np.ndarray:
    """Pose of a sensor looking down at ``target`` from ``distance`` metres above it.

    Parameters
    ----------
    target : (3,) base frame, metres
        The point on the optical axis at the height ``target[2]``.
    distance : float
        Height of the sensor above ``target[2]``, metres.
    tilt : float
        Angle of the optical axis from straight down, radians.
    azimuth : float
        Direction (about base z) the axis leans toward, radians.
    roll : float
        Rotation about the optical axis: the base direction (cos roll, sin roll, 0), made
        perpendicular to the axis, is the sensor's x, radians.

    Returns
    -------
    sensor_to_base : (4, 4) float64
    """
    z = np.array([math.sin(tilt) * math.cos(azimuth), math.sin(tilt) * math.sin(azimuth),
                  -math.cos(tilt)])
    h = np.array([math.cos(roll), math.sin(roll), 0.0])
    x = h - (h @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = np.asarray(target, dtype=np.float64) - (distance / math.cos(tilt)) * z
    return T


def _draw_pose(spec: SceneSpec, boxes: np.ndarray,
               rng: np.random.Generator) -> tuple[np.ndarray, float, float]:
    """The scene's sensor pose, aimed near the centre of the pile's top (or the pallet's,
    or the floor's): ``(sensor_to_base (4, 4), distance m, tilt rad)``, the spec's distance
    and tilt where it gives them, else drawn."""
    # Draw everything always, so a given distance or tilt does not shift the other draws.
    d, t = rng.uniform(1.0, 3.0), rng.uniform(0.0, 0.25)
    azimuth, roll = rng.uniform(0, 2 * math.pi, 2)
    aim = rng.normal(0.0, 0.03, 2)
    distance = float(d if spec.distance is None else spec.distance)
    tilt = float(t if spec.tilt is None else spec.tilt)
    if len(boxes):
        c = np.concatenate([_footprint_corners(b) for b in boxes])
        centre = (c.min(0) + c.max(0)) / 2
        z_top = float((boxes[:, 2] + boxes[:, 5] / 2).max())
    else:
        centre, z_top = np.zeros(2), (0.0 if spec.kind == "floor" else _PALLET_TOP)
    target = np.array([centre[0] + aim[0], centre[1] + aim[1], z_top])
    return look_down_pose(target, distance, tilt, azimuth, roll), distance, tilt

"""Simulate a scan: draw the layout and the pose, ray-cast the scene, take its ground truth,
then let the sensor measure it.

:func:`simulate` draws everything from the spec's seed; :func:`simulate_boxes` renders given
boxes from a given pose. Both go through one render, so the same spec gives the same arrays,
bit for bit.
"""

from __future__ import annotations

import dataclasses
import functools
import zlib
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from boxloc.errors import InputError
from boxloc.scan import PinholeModel, Scan
from boxloc.simulate.layouts import _decorations, _layout
from boxloc.simulate.pose import _draw_pose
from boxloc.simulate.raycast import _as_host_top, _build_world, _cast, _RayIndex
from boxloc.simulate.sensors import _measure, _rendered, _shadowed
from boxloc.simulate.spec import SceneSpec, format_spec, parse_spec
from boxloc.simulate.truth import GroundTruth, _ground_truth
from boxloc.simulate.zoo import draw_sensor, measure

__all__ = ["SimulatedScan", "simulate", "simulate_boxes"]

#: Capture times: a fixed epoch plus 0.1 s per seed (never the clock).
_EPOCH_NS = 1_700_000_000 * 10**9


@dataclass(frozen=True, eq=False)
class SimulatedScan:
    """A simulated scan, its ground truth, and the spec that made it.

    ``spec`` has ``distance`` and ``tilt`` resolved (the drawn values), so
    ``simulate(sim.spec)`` reproduces the scan bit for bit.
    """

    scan: Scan
    truth: GroundTruth
    spec: SceneSpec


def simulate(spec: SceneSpec | str, seed: int | None = None) -> SimulatedScan:
    """Simulate one scan of a piled-box scene, with its exact ground truth.

    Parameters
    ----------
    spec : SceneSpec or str
        The scene (a string is read by :func:`parse_spec`).
    seed : int, optional
        Overrides ``spec.seed``.

    Returns
    -------
    SimulatedScan
        ``scan`` (index 0, pinhole sensor, ``sensor_to_base`` set, capture time from the
        seed), ``truth`` and the spec with ``distance``/``tilt`` resolved.

    Raises
    ------
    InputError
        A bad spec.

    Notes
    -----
    Deterministic: the same spec gives the same arrays, bit for bit.
    """
    if isinstance(spec, str):
        spec = parse_spec(spec)
    if not isinstance(spec, SceneSpec):
        raise TypeError(f"spec must be a SceneSpec or a str, got {type(spec).__name__}")
    if seed is not None:
        spec = dataclasses.replace(spec, seed=seed)
    streams = _streams(spec)
    boxes = _layout(spec, streams[0])
    T, distance, tilt = _draw_pose(spec, boxes, streams[1])
    spec = dataclasses.replace(spec, distance=distance, tilt=tilt)
    return _render(spec, boxes, T, streams)


def simulate_boxes(boxes: npt.ArrayLike, sensor_to_base: npt.ArrayLike,
                   spec: SceneSpec | str | None = None, seed: int | None = None) -> SimulatedScan:
    """Render given boxes (on the pallet, on the floor) from a given pose.

    Parameters
    ----------
    boxes : array_like, shape (B, 7)
        Base frame: centre x, y, z, size x, y, z, yaw about z, metres and radians.
        The pallet's top is at ``PALLET_SIZE[2]``; a box standing on it has
        ``z = PALLET_SIZE[2] + size_z / 2``.
    sensor_to_base : array_like, shape (4, 4)
        The sensor pose, e.g. from :func:`look_down_pose`.
    spec : SceneSpec or str, optional
        Sensor and noise settings (its layout fields, ``distance`` and ``tilt`` are unused).
    seed : int, optional
        Overrides ``spec.seed`` (the noise).
    """
    if spec is None:
        spec = SceneSpec(kind="single")
    elif isinstance(spec, str):
        spec = parse_spec(spec)
    if seed is not None:
        spec = dataclasses.replace(spec, seed=seed)
    b = np.asarray(boxes, dtype=np.float64)
    if b.ndim != 2 or b.shape[1] != 7:
        raise InputError(f"boxes must have shape (B, 7), got {b.shape}")
    if not np.isfinite(b).all() or (b[:, 3:6] <= 2 * spec.bevel).any():
        raise InputError("boxes must be finite with sizes larger than twice the bevel")
    T = np.asarray(sensor_to_base, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InputError(f"sensor_to_base must be a finite (4, 4) matrix, got {T.shape}")
    if not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9):
        raise InputError("sensor_to_base must have an orthonormal rotation")
    return _render(spec, b, T, _streams(spec))


def _streams(spec: SceneSpec) -> list[np.random.Generator]:
    """Independent generators for the layout, the pose, the default sensor's noise, the
    decorations and the zoo's sensor (spawned children are fixed by their index, so the first
    three are what they were when there were three)."""
    ss = np.random.SeedSequence([spec.seed, zlib.crc32(spec.kind.encode())])
    return [np.random.default_rng(s) for s in ss.spawn(5)]


@functools.lru_cache(maxsize=4)
def _camera(width: int, height: int, f: float) -> tuple[PinholeModel, np.ndarray, _RayIndex]:
    """The sensor model, its unit rays (N, 3) and their index (cached: scenes share them)."""
    sensor = PinholeModel(f, f, (width - 1) / 2, (height - 1) / 2, width, height)
    rays = sensor.rays().reshape(-1, 3)
    rays.flags.writeable = False
    return sensor, rays, _RayIndex(rays, (height, width))


def _render(spec: SceneSpec, boxes: np.ndarray, T: np.ndarray,
            streams: list[np.random.Generator]) -> SimulatedScan:
    """Ray-cast ``boxes`` seen from ``T`` (sensor_to_base), take the truth, then measure."""
    H, W = spec.height, spec.width
    sensor, rays, index = _camera(W, H, float(spec.f))
    deco = _decorations(spec, boxes, streams[3]) if (spec.tape or spec.labels) else None
    world = _build_world(boxes, T, spec.bevel, spec.bulge, deco, spec.kind != "floor")
    r0, surf, normal = _cast(world, np.zeros(3), rays, index)
    r0 = np.where(np.isfinite(r0), r0, np.nan)
    # A decoration is part of its lid for the truth: its pixels see the host's top face.
    surf_t = _as_host_top(world, surf)
    truth, at_jump = _ground_truth(world, boxes, T, rays, r0, surf_t, (H, W), spec.f,
                                   spec.bevel)
    if spec.sensor is None:
        assert normal is not None
        shadow = (_shadowed(world, r0[:, None] * rays, surf, spec.baseline, spec.f, (H, W))
                  if spec.shadows else np.zeros(H * W, bool))
        rng_range = _measure(spec, world, sensor, rays, r0, normal, at_jump, shadow, streams[2])
    else:
        scale, cls = draw_sensor(spec.sensor, streams[4])
        spec = dataclasses.replace(
            spec, noise_scale=scale if spec.noise_scale is None else spec.noise_scale,
            sensor_class=cls if spec.sensor_class is None else spec.sensor_class)
        assert spec.noise_scale is not None
        ren = _rendered(spec, world, sensor, rays, r0, surf, surf_t, normal, at_jump)
        rng_range = measure(str(spec.sensor), ren, spec.noise_scale, spec.sensor_class, streams[4])
    scan = Scan(
        range=rng_range.reshape(H, W).astype(np.float32), sensor=sensor,
        capture_time_ns=_EPOCH_NS + (spec.seed % 2**31) * 100_000_000, index=0,
        sensor_to_base=T, source="simulate:" + format_spec(spec),
        meta={"simulator": spec.to_dict()},
    )
    return SimulatedScan(scan=scan, truth=truth, spec=spec)

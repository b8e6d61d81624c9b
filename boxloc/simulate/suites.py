"""The benchmarks' scene lists: :func:`scene_suite` (the default sensor, five kinds) and
:func:`matrix_suite` (every physical sensor x every kind).

A suite is a pure function of ``(n, seed)``, and a longer suite starts with the shorter one.
"""

from __future__ import annotations

import math

import numpy as np

from boxloc.errors import InputError
from boxloc.simulate.spec import SceneSpec
from boxloc.simulate.zoo import SENSORS

__all__ = ["MATRIX_KINDS", "scene_suite", "matrix_suite"]

#: The kinds of :func:`scene_suite` (fixed: new kinds do not change the benchmark's scenes).
_SUITE_KINDS = ("single", "pallet", "partial", "mixed", "touching")
#: The kinds of :func:`matrix_suite`.
MATRIX_KINDS = ("single", "pallet", "partial", "mixed", "touching", "layered", "empty", "floor")


def scene_suite(n: int, seed: int = 0) -> list[SceneSpec]:
    """The benchmark's scenes: every kind but ``empty`` in turn, varied distance, tilt, bulge.

    Parameters
    ----------
    n : int
        Number of scenes (>= 0).
    seed : int
        Seeds the draws; the same (n, seed) always gives the same list, and a longer suite
        starts with the shorter one.
    """
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 0:
        raise InputError(f"scene suite size must be an integer >= 0, got {n!r}")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise InputError(f"scene suite seed must be an integer >= 0, got {seed!r}")
    kinds = _SUITE_KINDS
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5C3E]))
    specs = []
    for i in range(int(n)):
        distance = round(float(rng.uniform(1.0, 3.0)), 3)
        tilt = round(float(rng.uniform(0.0, 0.25)), 4)
        bulge = round(float(rng.uniform(0.003, 0.015)), 4) if rng.random() < 0.4 else 0.0
        scene_seed = int(rng.integers(0, 2**31))
        specs.append(SceneSpec(kind=kinds[i % len(kinds)], seed=scene_seed, distance=distance,
                               tilt=tilt, bulge=bulge))
    return specs


#: Per sensor, the focal length at 640 px width (its field of view): the paper-class scanner
#: as the default camera, a Kinect v2 ToF (70 deg), a Kinect v1 (57 deg), an OAK-D-Pro (72 deg).
_MATRIX_F640 = {"laser": 525.0, "tof": 456.0, "structured-light": 580.0, "active-stereo": 440.0}
_MATRIX_SIZES = ((320, 240), (640, 480), (960, 720), (1280, 960))


def matrix_suite(n: int, seed: int = 0) -> list[SceneSpec]:
    """Scenes of the sensor x scene-kind matrix benchmark.

    Scene ``i`` has sensor ``SENSORS[i % 4]`` and kind ``MATRIX_KINDS[(i // 4) % 8]``, so
    every 32 scenes fill each cell once. Each draws: the camera 1-3.5 m above the top of the
    pile (the floor for ``floor``), tilted 0-30 deg; the resolution among 320x240, 640x480,
    960x720 and 1280x960 (the focal length follows the sensor's field of view); a bevel of
    0-5 mm (none on a third of the scenes, and never on ``layered``: sharp touching edges);
    a lid bulge on 40 %; tape and labels on half. The noise scale (0.5-3x) and the
    active-stereo class are left to the scene seed.

    Parameters
    ----------
    n : int
        Number of scenes (>= 0).
    seed : int
        Seeds the draws; the same (n, seed) gives the same list, and a longer suite starts
        with the shorter one.
    """
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 0:
        raise InputError(f"matrix suite size must be an integer >= 0, got {n!r}")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise InputError(f"matrix suite seed must be an integer >= 0, got {seed!r}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x3A7F]))
    return [draw_matrix_spec(rng, SENSORS[i % len(SENSORS)],
                             MATRIX_KINDS[(i // len(SENSORS)) % len(MATRIX_KINDS)])
            for i in range(int(n))]


def draw_matrix_spec(rng: np.random.Generator, sensor: str, kind: str) -> SceneSpec:
    """One scene of the matrix's distribution (see :func:`matrix_suite`) for a given sensor
    and kind, drawn from ``rng`` (the same draws, in the same order, for every kind)."""
    distance = round(float(rng.uniform(1.0, 3.5)), 3)
    tilt = round(float(rng.uniform(0.0, math.radians(30.0))), 4)
    w, h = _MATRIX_SIZES[int(rng.integers(len(_MATRIX_SIZES)))]
    sharp, bevel = rng.random() < 1 / 3, round(float(rng.uniform(0.0005, 0.005)), 4)
    bulge = round(float(rng.uniform(0.003, 0.015)), 4) if rng.random() < 0.4 else 0.0
    deco = rng.random() < 0.5
    scene_seed = int(rng.integers(0, 2**31))
    return SceneSpec(
        kind=kind, seed=scene_seed, width=w, height=h,
        f=round(_MATRIX_F640[sensor] * w / 640, 3), distance=distance, tilt=tilt,
        bevel=0.0 if (sharp or kind == "layered") else bevel, bulge=bulge, sensor=sensor,
        tape=0.6 if deco else 0.0, labels=0.5 if deco else 0.0)

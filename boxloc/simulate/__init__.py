"""Piled-box scenes with exact ground truth: a seeded, reproducible range-sensor simulator.

A scene is a pile of cartons on a pallet on a floor, seen from above by a range sensor.
Everything is ray-cast analytically (each box is a convex polyhedron: six faces plus four
45-degree bevels along its top edges; the pallet is a slab; the floor a plane), then the
sensor's artefacts are added: range noise from :class:`boxloc.scan.NoiseModel` (growing with
range and incidence), beam pointing jitter, mixed pixels at depth jumps, emitter shadows,
random dropouts, and optionally a cardboard bulge of the box tops.

Frames and units
----------------
Metres and radians. The *base* frame has z up with the floor at z = 0; the pallet (1.2 x 0.8 x
0.144 m) is centred on the origin with its long side along x. The *sensor* frame is x right,
y down, z forward (the optical axis). Ground truth is given in the sensor frame.

Ground truth
------------
One row per top face of every box (``F == B``; a face hidden under another box is still a
row, with ``visible_fraction`` near 0). A face is *fully exposed* (graspable, the paper's
target) when no box rests on it and at least 90 % of its area is seen. The per-pixel maps
come from the noise-free render: ``face_ids`` (which top face each pixel sees; the bevel
band belongs to the face, since the face is the full nominal rectangle) and ``edge_labels``
(1 jump on the nearer side of a depth discontinuity, 2 crease where two surfaces meet).

Modules, in the order the data flows
------------------------------------
:mod:`~boxloc.simulate.spec`
    :class:`SceneSpec` and its text form (:func:`parse_spec`, :func:`format_spec`).
:mod:`~boxloc.simulate.boxes`
    The pallet and box footprints (corners, separation, which box rests on which).
:mod:`~boxloc.simulate.layouts`
    The boxes of each scene kind, and the tape and labels on their lids.
:mod:`~boxloc.simulate.pose`
    The sensor looking down at the pile (:func:`look_down_pose`).
:mod:`~boxloc.simulate.raycast`
    The scene as half-spaces in the sensor frame, and the rays cast at it.
:mod:`~boxloc.simulate.truth`
    :class:`GroundTruth`: faces, visible fractions, face and edge maps.
:mod:`~boxloc.simulate.sensors`
    The default sensor's measurement, and the render handed to the zoo.
:mod:`~boxloc.simulate.zoo`
    The physical sensor models (:data:`SENSORS`).
:mod:`~boxloc.simulate.scene`
    :func:`simulate` and :func:`simulate_boxes`, which run all of the above.
:mod:`~boxloc.simulate.suites`
    The benchmarks' scene lists (:func:`scene_suite`, :func:`matrix_suite`).
:mod:`~boxloc.simulate.files`
    ``.npz`` files with their truth, and the ``boxloc simulate`` command's paths.

Example
-------
>>> sim = simulate("pallet:seed=3,distance=2.0")
>>> sim.scan.range.shape, len(sim.truth) == sim.truth.boxes.shape[0]
((480, 640), True)
"""

from __future__ import annotations

from boxloc.simulate.boxes import PALLET_SIZE
from boxloc.simulate.files import (
    load_truth,
    output_paths,
    save_npz,
    simulate_to_files,
    summary_line,
)
from boxloc.simulate.pose import look_down_pose
from boxloc.simulate.scene import SimulatedScan, simulate, simulate_boxes
from boxloc.simulate.spec import KINDS, PATTERNS, SceneSpec, format_spec, override_spec, parse_spec
from boxloc.simulate.suites import MATRIX_KINDS, matrix_suite, scene_suite
from boxloc.simulate.truth import GroundTruth
from boxloc.simulate.zoo import SENSORS

__all__ = [
    "KINDS",
    "PATTERNS",
    "PALLET_SIZE",
    "SceneSpec",
    "GroundTruth",
    "SimulatedScan",
    "parse_spec",
    "format_spec",
    "override_spec",
    "simulate",
    "simulate_boxes",
    "look_down_pose",
    "scene_suite",
    "matrix_suite",
    "MATRIX_KINDS",
    "SENSORS",
    "save_npz",
    "load_truth",
    "output_paths",
    "simulate_to_files",
    "summary_line",
]

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

Example
-------
>>> sim = simulate("pallet:seed=3,distance=2.0")
>>> sim.scan.range.shape, len(sim.truth) == sim.truth.boxes.shape[0]
((480, 640), True)
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import typing
import zipfile
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from boxloc.errors import InputError
from boxloc.products import from_arrays, to_arrays
from boxloc.scan import NoiseModel, PinholeModel, Scan
from boxloc.simulate.zoo import SENSORS, STEREO_CLASSES, Rendered, draw_sensor, measure

__all__ = [
    "KINDS",
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

KINDS = ("single", "pallet", "partial", "mixed", "touching", "empty", "layered", "floor")
#: The kinds of :func:`scene_suite` (fixed: new kinds do not change the benchmark's scenes).
_SUITE_KINDS = ("single", "pallet", "partial", "mixed", "touching")
#: The kinds of :func:`matrix_suite`.
MATRIX_KINDS = ("single", "pallet", "partial", "mixed", "touching", "layered", "empty", "floor")

#: The pallet slab (x, y, z extent), metres; centred on the base origin, standing on z = 0.
PALLET_SIZE = (1.2, 0.8, 0.144)

_PALLET_TOP = PALLET_SIZE[2]
#: Half-spaces per object: 6 faces and 4 top-edge bevels (padded with always-true rows).
_K = 10
_TOP = 4  # index of the top face among an object's half-spaces
_FACE_PLANES = (4, 6, 7, 8, 9)  # a box's top and its bevels: the nominal top rectangle
#: Box footprints that overlap by more than this (every axis) are "resting on" each other.
_REST_OVERLAP = 0.001
#: Surfaces of different objects whose meeting line is within this of both (plus the bevel)
#: are in contact: a gap of a few mm is below what a range sensor resolves as a jump.
_CONTACT_TOL = 0.005
#: A shadow is cast only by an occluder this much in front of the lit point, metres.
_SHADOW_EPS = 1e-4
#: Capture times: a fixed epoch plus 0.1 s per seed (never the clock).
_EPOCH_NS = 1_700_000_000 * 10**9
_FULLY_SEEN = 0.9  # the visible fraction above which a free face is graspable
_PLACE_TRIES = 60  # placement attempts per box in the "mixed" layout
_TILE = 16  # ray-index tile size, pixels

_JSON_SEP = (",", ":")


# --- the specification ---------------------------------------------------------------------------


@dataclass(frozen=True)
class SceneSpec:
    """What to simulate. Every field has a default; ``parse_spec`` reads the text form.

    Parameters
    ----------
    kind : str
        One of :data:`KINDS`: ``layered`` is a pallet of layers packed with zero gaps and no
        jitter (boxes touching along whole faces); ``floor`` is the bare floor (no pallet, no
        boxes); ``empty`` the bare pallet.
    seed : int
        Seeds the layout, the sensor pose and the noise (three independent streams).
    width, height : int
        Image size, pixels.
    f : float
        Focal length, pixels (fx = fy); the principal point is the image centre.
    distance : float or None
        Sensor height above the pile top, metres; None draws it in [1, 3].
    tilt : float or None
        Angle of the optical axis from straight down, radians; None draws it in [0, 0.25].
    noise : NoiseModel
        Range noise; the default is the localizer's default (``Config().noise``).
    dropout : float
        Probability that a pixel returns nothing, independently per pixel.
    mixed_pixels : bool
        Pixels straddling a depth jump average the ranges of their footprint (2x2 samples),
        each with probability ``mixed_fraction``.
    shadows : bool
        No return where the emitter, ``baseline`` metres along sensor x, cannot see the point.
    bulge : float
        Cardboard bulge at the centre of each top face, metres, toward the sensor:
        ``bulge * (1 - (2u/w)^2) * (1 - (2v/l)^2)``.
    bevel : float
        Rounded top edge of the cartons: the outer ``bevel`` metres of each top face slope
        down at 45 degrees (a seam between touching boxes shows as a shallow V groove).
    min_edge, max_edge : float
        Range of box footprint edges, metres.
    min_height, max_height : float
        Range of box heights, metres.
    layers : int or None
        Layers of a ``pallet``/``partial`` scene; None draws 1-3 (``partial``: 2-3).
    n_boxes : int or None
        Boxes of a ``mixed`` (default 4-10; fewer if they do not fit) or ``touching`` scene
        (default 2-4, fewer if the row is longer than the pallet; a requested count is kept
        by narrowing the boxes).
    max_gap : float or None
        Largest gap between neighbouring boxes, metres; None: 5 mm on pallets, 2 mm for
        ``touching``.
    jitter : float
        Largest position jitter of a pallet box, metres (kept inside its cell, so boxes never
        interpenetrate).
    yaw_jitter : float
        Largest yaw jitter of a pallet box, radians.
    mixed_fraction : float
        Probability that a pixel at a jump becomes a mixed pixel.
    baseline : float
        Emitter offset along sensor x, metres (for shadows).
    sensor : str or None
        A physical sensor model of :mod:`boxloc.simulate.zoo` (``laser``, ``tof``,
        ``structured-light``, ``active-stereo``); None is the default sensor, whose noise is
        ``noise`` (with ``dropout``, ``mixed_pixels``, ``shadows``, ``mixed_fraction`` and
        ``baseline``, which the zoo's sensors do not use: they carry their own artefacts).
    noise_scale : float or None
        A zoo sensor's noise times its nominal; None draws it log-uniformly in [0.5, 3]
        from the seed.
    sensor_class : str or None
        ``active-stereo`` only: ``oak-d-pro`` or ``realsense``; None draws it.
    tape, labels : float
        Probability that a box with nothing on it has packing tape along its lid (1-3 mm
        thick), and a label (0.5-2 mm thick). Neither is a box top in the ground truth: the
        pixels that see them belong to the lid under them.
    """

    kind: str = "pallet"
    seed: int = 0
    width: int = 640
    height: int = 480
    f: float = 525.0
    distance: float | None = None
    tilt: float | None = None
    noise: NoiseModel = field(default_factory=NoiseModel)
    dropout: float = 0.002
    mixed_pixels: bool = True
    shadows: bool = True
    bulge: float = 0.0
    bevel: float = 0.004
    min_edge: float = 0.15
    max_edge: float = 0.6
    min_height: float = 0.1
    max_height: float = 0.4
    layers: int | None = None
    n_boxes: int | None = None
    max_gap: float | None = None
    jitter: float = 0.003
    yaw_jitter: float = math.radians(1.0)
    mixed_fraction: float = 0.5
    baseline: float = 0.075
    sensor: str | None = None
    noise_scale: float | None = None
    sensor_class: str | None = None
    tape: float = 0.0
    labels: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.noise, NoiseModel):
            raise TypeError(f"scene noise must be a NoiseModel, got {type(self.noise).__name__}")

        def check(name: str, ok: bool, what: str) -> None:
            if not ok:
                raise InputError(f"scene {name} must be {what}, got {getattr(self, name)!r}")

        def num(name: str) -> float:
            v = getattr(self, name)
            check(name, isinstance(v, int | float) and not isinstance(v, bool)
                  and math.isfinite(v), "a finite number")
            return float(v)

        def integer(name: str) -> int:
            v = getattr(self, name)
            check(name, isinstance(v, int | np.integer) and not isinstance(v, bool),
                  "an integer")
            return int(v)

        check("kind", self.kind in KINDS, "one of " + ", ".join(KINDS))
        check("seed", 0 <= integer("seed") < 2**63, "in [0, 2**63)")
        check("width", 8 <= integer("width") <= 8192, "in [8, 8192]")
        check("height", 8 <= integer("height") <= 8192, "in [8, 8192]")
        check("f", num("f") > 0, "> 0")
        if self.distance is not None:
            check("distance", 0.3 <= num("distance") <= 20, "in [0.3, 20] m or none")
        if self.tilt is not None:
            check("tilt", 0 <= num("tilt") <= 1.0, "in [0, 1] rad or none")
        check("dropout", 0 <= num("dropout") < 1, "in [0, 1)")
        check("mixed_pixels", isinstance(self.mixed_pixels, bool), "true or false")
        check("shadows", isinstance(self.shadows, bool), "true or false")
        check("bulge", 0 <= num("bulge") <= 0.05, "in [0, 0.05] m")
        check("bevel", 0 <= num("bevel") <= 0.02, "in [0, 0.02] m")
        check("min_edge", 0.05 <= num("min_edge") <= num("max_edge"), "in [0.05, max_edge] m")
        check("max_edge", num("max_edge") <= 0.8, "<= 0.8 m (the pallet's width)")
        check("min_height", 0.03 <= num("min_height") <= num("max_height"),
              "in [0.03, max_height] m")
        check("max_height", num("max_height") <= 1.0, "<= 1 m")
        check("bevel", self.bevel < min(self.min_edge, self.min_height) / 2,
              "smaller than half the smallest box dimension")
        if self.layers is not None:
            check("layers", 1 <= integer("layers") <= 5, "in [1, 5] or none")
        if self.n_boxes is not None:
            check("n_boxes", 1 <= integer("n_boxes") <= 30, "in [1, 30] or none")
        if self.max_gap is not None:
            check("max_gap", 0 <= num("max_gap") <= 0.05, "in [0, 0.05] m or none")
        check("jitter", 0 <= num("jitter") <= 0.05, "in [0, 0.05] m")
        check("yaw_jitter", 0 <= num("yaw_jitter") <= 0.2, "in [0, 0.2] rad")
        check("mixed_fraction", 0 <= num("mixed_fraction") <= 1, "in [0, 1]")
        check("baseline", 0 <= num("baseline") <= 0.5, "in [0, 0.5] m")
        check("sensor", self.sensor is None or self.sensor in SENSORS,
              "one of " + ", ".join(SENSORS) + " or none")
        if self.noise_scale is not None:
            check("noise_scale", self.sensor is not None, "none without a sensor")
            check("noise_scale", 0.05 <= num("noise_scale") <= 20, "in [0.05, 20] or none")
        if self.sensor_class is not None:
            check("sensor_class", self.sensor == "active-stereo"
                  and self.sensor_class in STEREO_CLASSES,
                  "one of " + ", ".join(STEREO_CLASSES) + " with sensor=active-stereo, or none")
        check("tape", 0 <= num("tape") <= 1, "in [0, 1]")
        check("labels", 0 <= num("labels") <= 1, "in [0, 1]")

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (the noise model nested).

        The zoo and decoration fields appear only when they differ from their defaults, so a
        default scene's dict (recorded in logs and ``.npz`` files) is what it was before they
        existed.
        """
        d = dataclasses.asdict(self)
        d["noise"] = self.noise.to_dict()
        for name, default in _NEW_FIELDS.items():
            if d[name] == default:
                del d[name]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SceneSpec:
        """Inverse of :meth:`to_dict`; unknown keys raise InputError."""
        d = dict(d)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise InputError(f"unknown scene key(s): {', '.join(unknown)}")
        if isinstance(d.get("noise"), dict):
            nk = {f.name for f in dataclasses.fields(NoiseModel)}
            bad = sorted(set(d["noise"]) - nk)
            if bad:
                raise InputError(f"unknown scene key(s): {', '.join('noise.' + b for b in bad)}")
            d["noise"] = NoiseModel(**{k: float(v) for k, v in d["noise"].items()})
        return cls(**d)


#: Fields added with the sensor zoo, and their defaults (left out of ``to_dict`` at default).
_NEW_FIELDS: dict[str, Any] = {"sensor": None, "noise_scale": None, "sensor_class": None,
                               "tape": 0.0, "labels": 0.0}


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """The exact answer for one simulated scan (sensor frame, metres).

    Attributes
    ----------
    centers : (F, 3) float64
        Centre of each box's top face.
    normals : (F, 3) float64
        Unit normal, pointing toward the sensor.
    x_axis, y_axis : (F, 3) float64
        Unit axes along the width and the length; ``x_axis x y_axis == normals``.
    width, length : (F,) float64
        Face dimensions, ``width <= length``.
    corners : (F, 4, 3) float64
        ``c - x w/2 - y l/2``, then ``+x``, ``+x+y``, ``+y``: counter-clockwise seen from the
        sensor.
    visible_fraction : (F,) float64
        Fraction of the face area the sensor sees (``face_ids`` of the noise-free render,
        each pixel weighted by its footprint on the face plane); 0..1. Emitter shadows,
        dropouts and noise do not lower it: they are the sensor's, not the pile's.
    fully_exposed : (F,) bool
        Nothing rests on the face and ``visible_fraction >= 0.9``: the graspable faces.
    box_index : (F,) int32
        The box (row of ``boxes``) of each face.
    face_ids : (H, W) int32
        Top face seen at each pixel by the noise-free render (bevel band included), else -1.
    edge_labels : (H, W) uint8
        0 none, 1 jump (on the nearer side), 2 crease, from the noise-free render.
    boxes : (B, 7) float64
        Base frame: centre x, y, z, size x, y, z, yaw about z.
    sensor_to_base : (4, 4) float64
    """

    centers: np.ndarray
    normals: np.ndarray
    x_axis: np.ndarray
    y_axis: np.ndarray
    width: np.ndarray
    length: np.ndarray
    corners: np.ndarray
    visible_fraction: np.ndarray
    fully_exposed: np.ndarray
    box_index: np.ndarray
    face_ids: np.ndarray
    edge_labels: np.ndarray
    boxes: np.ndarray
    sensor_to_base: np.ndarray

    _DTYPES: typing.ClassVar[dict[str, Any]] = {
        "fully_exposed": np.bool_, "box_index": np.int32, "face_ids": np.int32,
        "edge_labels": np.uint8,
    }

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            a = np.array(getattr(self, f.name), dtype=self._DTYPES.get(f.name, np.float64),
                         order="C", copy=True)
            a.flags.writeable = False
            object.__setattr__(self, f.name, a)

    def __len__(self) -> int:
        return int(self.centers.shape[0])


@dataclass(frozen=True, eq=False)
class SimulatedScan:
    """A simulated scan, its ground truth, and the spec that made it.

    ``spec`` has ``distance`` and ``tilt`` resolved (the drawn values), so
    ``simulate(sim.spec)`` reproduces the scan bit for bit.
    """

    scan: Scan
    truth: GroundTruth
    spec: SceneSpec


# --- parsing -------------------------------------------------------------------------------------


def _parse_value(key: str, text: str, annotation: str) -> Any:
    """One ``key=value`` value, typed by the field's annotation."""
    t = text.strip()
    low = t.lower()
    optional = "None" in annotation
    if optional and low in ("none", "null", ""):
        return None
    try:
        if annotation.startswith("bool"):
            if low in ("1", "true", "yes", "on"):
                return True
            if low in ("0", "false", "no", "off"):
                return False
            raise ValueError
        if annotation.startswith("int"):
            return int(t)
        if annotation.startswith("float"):
            v = float(t)
            if not math.isfinite(v):
                raise ValueError
            return v
        if annotation.startswith("str"):
            return t
    except ValueError:
        pass
    want = annotation.replace(" | None", " or none")
    raise InputError(f"scene spec: {key}={text!r} is not a valid {want}")


def parse_spec(text: str) -> SceneSpec:
    """Parse ``KIND[:key=value,...]``, e.g. ``"mixed:seed=3,distance=2.0,bulge=0.01"``.

    Keys are :class:`SceneSpec` fields; ``noise.<name>`` sets a :class:`NoiseModel` field.

    Raises
    ------
    InputError
        Unknown kind or key, an item that is not ``key=value``, a repeated key, or a value of
        the wrong type or out of range; the message names it.
    """
    if not isinstance(text, str):
        raise InputError(f"scene spec must be a string, got {type(text).__name__}")
    kind, _, rest = text.strip().partition(":")
    kind = kind.strip().lower()
    if kind not in KINDS:
        raise InputError(f"unknown scene kind {kind!r}; expected one of {', '.join(KINDS)}")
    hints = {f.name: str(f.type) for f in dataclasses.fields(SceneSpec)}
    noise_hints = {f.name: str(f.type) for f in dataclasses.fields(NoiseModel)}
    kw: dict[str, Any] = {}
    noise_kw: dict[str, float] = {}
    for key, val in _spec_items(rest.split(",")):
        if key in kw or (key.startswith("noise.") and key.removeprefix("noise.") in noise_kw):
            raise InputError(f"scene spec key {key!r} is given twice")
        if key.startswith("noise."):
            name = key.removeprefix("noise.")
            if name not in noise_hints:
                raise InputError(f"unknown scene key {key!r}; noise keys: "
                                 + ", ".join("noise." + k for k in noise_hints))
            noise_kw[name] = _parse_value(key, val, noise_hints[name])
        elif key in hints and key not in ("kind", "noise"):
            kw[key] = _parse_value(key, val, hints[key])
        else:
            keys = [k for k in hints if k not in ("kind", "noise")] + ["noise.<name>"]
            raise InputError(f"unknown scene key {key!r}; expected one of {', '.join(keys)}")
    if noise_kw:
        kw["noise"] = NoiseModel(**noise_kw)
    return SceneSpec(kind=kind, **kw)


def override_spec(spec: SceneSpec, items: Sequence[str]) -> SceneSpec:
    """``spec`` with ``key=value`` items (as in :func:`parse_spec`) replacing its fields.

    Raises
    ------
    InputError
        As :func:`parse_spec`, naming the item.
    """
    kind, _, rest = format_spec(spec).partition(":")
    kv = dict(_spec_items([*rest.split(","), *items]))  # later items replace earlier ones
    return parse_spec(kind + ":" + ",".join(f"{k}={v}" for k, v in kv.items()))


def _spec_items(items: Sequence[str]) -> Iterator[tuple[str, str]]:
    """(key, value) of each non-empty ``key=value`` item, stripped."""
    for item in items:
        item = item.strip()
        if not item:
            continue
        if "=" not in item:
            raise InputError(f"scene spec item {item!r} must be key=value")
        key, val = (t.strip() for t in item.split("=", 1))
        yield key, val


def format_spec(spec: SceneSpec) -> str:
    """The text form of a spec (only the fields that differ from the defaults).

    ``parse_spec(format_spec(s)) == s`` for every spec.
    """
    default = SceneSpec()
    items = []
    for f in dataclasses.fields(SceneSpec):
        if f.name in ("kind", "noise"):
            continue
        v = getattr(spec, f.name)
        if v != getattr(default, f.name) or f.name == "seed":
            text = "none" if v is None else v if isinstance(v, str) else repr(v).lower()
            items.append(f"{f.name}={text}")
    for f in dataclasses.fields(NoiseModel):
        v = getattr(spec.noise, f.name)
        if v != getattr(default.noise, f.name):
            items.append(f"noise.{f.name}={v!r}")
    return spec.kind + ":" + ",".join(items)


# --- geometry helpers ----------------------------------------------------------------------------


def _footprint_sep(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Separating-axis distance of box footprints (rotated rectangles), metres.

    Parameters
    ----------
    a : (N, 7), b : (M, 7) float64
        Boxes (cx, cy, cz, sx, sy, sz, yaw).

    Returns
    -------
    (N, M) float64
        Positive: the footprints are disjoint, at least this far apart along some axis.
        Negative: they overlap, by at least ``-sep`` along every axis.
    """
    d = b[None, :, :2] - a[:, None, :2]
    ca, sa = np.cos(a[:, 6])[:, None], np.sin(a[:, 6])[:, None]
    cb, sb = np.cos(b[:, 6])[None, :], np.sin(b[:, 6])[None, :]
    hxa, hya = a[:, 3, None] / 2, a[:, 4, None] / 2
    hxb, hyb = b[None, :, 3] / 2, b[None, :, 4] / 2
    sep = np.full(d.shape[:2], -np.inf)
    for ax, ay in ((ca, sa), (-sa, ca), (cb, sb), (-sb, cb)):
        ra = hxa * np.abs(ca * ax + sa * ay) + hya * np.abs(-sa * ax + ca * ay)
        rb = hxb * np.abs(cb * ax + sb * ay) + hyb * np.abs(-sb * ax + cb * ay)
        gap = np.abs(d[..., 0] * ax + d[..., 1] * ay) - ra - rb
        sep = np.maximum(sep, gap)
    return sep


def _footprint_corners(box: np.ndarray) -> np.ndarray:
    """(4, 2) corners of a box's footprint in the base xy plane."""
    c, s = math.cos(box[6]), math.sin(box[6])
    hx, hy = box[3] / 2, box[4] / 2
    local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    return box[:2] + local @ np.array([[c, s], [-s, c]])


def _collides(box: np.ndarray, placed: list[np.ndarray], clearance: float) -> bool:
    """Whether ``box`` comes closer than ``clearance`` to a placed box at overlapping heights."""
    if not placed:
        return False
    P = np.asarray(placed)
    lo, hi = box[2] - box[5] / 2, box[2] + box[5] / 2
    z_overlap = (np.minimum(hi, P[:, 2] + P[:, 5] / 2)
                 - np.maximum(lo, P[:, 2] - P[:, 5] / 2)) > 1e-9
    sep = _footprint_sep(box[None], P)[0]
    return bool((z_overlap & (sep < clearance - 1e-12)).any())


def _rests_on(boxes: np.ndarray) -> np.ndarray:
    """``covered[i]``: some box rests on box i's top, shape (B,), bool."""
    B = len(boxes)
    if B == 0:
        return np.zeros(0, bool)
    top = boxes[:, 2] + boxes[:, 5] / 2
    bottom = boxes[:, 2] - boxes[:, 5] / 2
    touching = np.abs(bottom[None, :] - top[:, None]) < 1e-6  # [i, j]: j's bottom on i's top
    overlap = _footprint_sep(boxes, boxes) < -_REST_OVERLAP
    on = touching & overlap
    np.fill_diagonal(on, False)
    return np.asarray(on.any(1), dtype=bool)


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


# --- layouts (base frame) ------------------------------------------------------------------------


def _sizes(spec: SceneSpec, rng: np.random.Generator) -> tuple[float, float, float]:
    a, b = np.sort(rng.uniform(spec.min_edge, spec.max_edge, 2))
    return float(a), float(b), float(rng.uniform(spec.min_height, spec.max_height))


def _layout_single(spec: SceneSpec, rng: np.random.Generator) -> np.ndarray:
    a, b, h = _sizes(spec, rng)
    yaw = rng.uniform(-math.pi / 2, math.pi / 2)
    xy = rng.uniform(-0.1, 0.1, 2)
    return np.array([[xy[0], xy[1], _PALLET_TOP + h / 2, b, a, h, yaw]])


def _grid(a: float, b: float, g: float, orient: int) -> tuple[int, int, float, float]:
    """Cells of a pallet layer: (nx, ny, size x, size y); orient 1 turns the boxes 90 deg."""
    sx, sy = (b, a) if orient == 0 else (a, b)
    nx = int((PALLET_SIZE[0] + g + 1e-9) // (sx + g))
    ny = int((PALLET_SIZE[1] + g + 1e-9) // (sy + g))
    return nx, ny, sx, sy


def _layout_pallet(spec: SceneSpec, rng: np.random.Generator, partial: bool) -> np.ndarray:
    """Neat layers of one box size; ``partial`` unloads part of the top layer."""
    max_gap = 0.005 if spec.max_gap is None else spec.max_gap
    need = 2 if partial else 1
    a, b, h = _sizes(spec, rng)
    g = float(rng.uniform(0, max_gap))
    for _ in range(50):  # partial needs >= 2 boxes per layer; shrink the draw until they fit
        counts = [n[0] * n[1] for n in (_grid(a, b, g, 0)[:2], _grid(a, b, g, 1)[:2])]
        if max(counts) >= need:
            break
        a, b = max(spec.min_edge, 0.9 * a), max(spec.min_edge, 0.9 * b)
    if spec.layers is not None:
        n_layers = spec.layers
    else:
        n_layers = int(rng.integers(2, 4) if partial else rng.integers(1, 4))
    best = int(np.argmax(counts))
    # Real pallets interlock: alternate layers turn 90 deg when that loses few boxes.
    interlock = rng.random() < 0.5 and counts[1 - best] >= max(1, math.ceil(0.7 * counts[best]))
    boxes: list[np.ndarray] = []
    for layer in range(n_layers):
        orient = (1 - best) if (interlock and layer % 2 == 1) else best
        nx, ny, sx, sy = _grid(a, b, g, orient)
        ext_x, ext_y = nx * sx + (nx - 1) * g, ny * sy + (ny - 1) * g
        off = rng.uniform(-0.5, 0.5, 2) * 0.5 * np.array(
            [PALLET_SIZE[0] - ext_x, PALLET_SIZE[1] - ext_y])
        z = _PALLET_TOP + layer * h + h / 2
        for ix in range(nx):
            for iy in range(ny):
                cx = off[0] - ext_x / 2 + sx / 2 + ix * (sx + g)
                cy = off[1] - ext_y / 2 + sy / 2 + iy * (sy + g)
                j = rng.uniform(-1, 1, 3) * np.array([spec.jitter, spec.jitter, spec.yaw_jitter])
                boxes.append(_jitter_in_cell(cx, cy, z, sx, sy, h, g, j))
    out = np.asarray(boxes)
    if partial:
        top = np.flatnonzero(np.isclose(out[:, 2], out[:, 2].max()))
        if len(top) >= 2:
            # Unload from one side, as a robot or a person would.
            theta = rng.uniform(0, 2 * math.pi)
            order = top[np.argsort(out[top, 0] * math.cos(theta) + out[top, 1] * math.sin(theta),
                                   kind="stable")]
            n_remove = int(rng.integers(1, len(top)))
            out = np.delete(out, order[:n_remove], axis=0)
    return out


def _jitter_in_cell(cx: float, cy: float, z: float, sx: float, sy: float, h: float, g: float,
                    j: np.ndarray) -> np.ndarray:
    """A box jittered by ``j`` = (dx, dy, dyaw), shrunk until it stays inside its cell."""
    for scale in (1.0, 0.5, 0.25, 0.125):
        box = np.array([cx + scale * j[0], cy + scale * j[1], z, sx, sy, h, scale * j[2]])
        c = _footprint_corners(box)
        if (np.abs(c[:, 0] - cx) <= (sx + g) / 2 + 1e-12).all() and \
                (np.abs(c[:, 1] - cy) <= (sy + g) / 2 + 1e-12).all():
            return box
    return np.array([cx, cy, z, sx, sy, h, 0.0])


def _layout_mixed(spec: SceneSpec, rng: np.random.Generator) -> np.ndarray:
    """Boxes of different sizes and yaw, without overlap, some stacked on others."""
    n = spec.n_boxes if spec.n_boxes is not None else int(rng.integers(4, 11))
    hx, hy = PALLET_SIZE[0] / 2, PALLET_SIZE[1] / 2
    overhang = 0.03
    placed: list[np.ndarray] = []
    for _ in range(n):
        for _try in range(_PLACE_TRIES):
            a, b, h = _sizes(spec, rng)
            yaw = float(rng.uniform(-math.pi / 2, math.pi / 2))
            u = rng.uniform(-1, 1, 2)
            stack = bool(placed) and rng.random() < 0.35
            s = placed[int(rng.integers(len(placed)))] if placed else None
            if stack and s is not None:
                xy = s[:2] + _rot_z(s[6]) @ (u * s[3:5] / 2)
                box = np.array([xy[0], xy[1], s[2] + s[5] / 2 + h / 2, b, a, h, yaw])
                # Fully on the support's top, so it is stable and rests on exactly that box.
                local = (_footprint_corners(box) - s[:2]) @ _rot_z(s[6])
                if (np.abs(local) > s[3:5] / 2 + 1e-12).any():
                    continue
            else:
                xy = u * np.array([hx, hy])
                box = np.array([xy[0], xy[1], _PALLET_TOP + h / 2, b, a, h, yaw])
                c = _footprint_corners(box)
                if (np.abs(c[:, 0]) > hx + overhang).any() or \
                        (np.abs(c[:, 1]) > hy + overhang).any():
                    continue
            if not _collides(box, placed, clearance=0.003):
                placed.append(box)
                break
    return np.asarray(placed).reshape(-1, 7)


def _layout_touching(spec: SceneSpec, rng: np.random.Generator) -> np.ndarray:
    """2-4 boxes of equal height in a row along x, touching (gaps 0-2 mm)."""
    n = spec.n_boxes if spec.n_boxes is not None else int(rng.integers(2, 5))
    max_gap = 0.002 if spec.max_gap is None else spec.max_gap
    h = float(rng.uniform(spec.min_height, spec.max_height))
    sx = rng.uniform(spec.min_edge, spec.max_edge, n)
    sy = rng.uniform(spec.min_edge, spec.max_edge, n)
    gaps = rng.uniform(0, max_gap, max(n - 1, 0))
    dy = rng.uniform(-0.03, 0.03, n)
    shift = rng.uniform(-0.5, 0.5)
    # A drawn count gives way to the box sizes; a requested one is kept (boxes narrowed).
    while spec.n_boxes is None and n > 2 and sx[:n].sum() + gaps[: n - 1].sum() > PALLET_SIZE[0]:
        n -= 1
    sx, sy, gaps, dy = sx[:n], sy[:n], gaps[: n - 1], dy[:n]
    room = PALLET_SIZE[0] - gaps.sum()
    if sx.sum() > room:  # the row does not fit on the pallet: narrow the boxes
        sx = sx * room / sx.sum()
    total = sx.sum() + gaps.sum()
    x0 = -total / 2 + shift * (PALLET_SIZE[0] - total)
    left = x0 + np.concatenate([[0.0], np.cumsum(sx[:-1] + gaps)])
    cy = np.clip(dy, -(PALLET_SIZE[1] / 2 - sy / 2), PALLET_SIZE[1] / 2 - sy / 2)
    cy = np.where(sy / 2 > PALLET_SIZE[1] / 2, 0.0, cy)
    return np.stack([left + sx / 2, cy, np.full(n, _PALLET_TOP + h / 2), sx, sy,
                     np.full(n, h), np.zeros(n)], 1)


def _layout(spec: SceneSpec, rng: np.random.Generator) -> np.ndarray:
    if spec.kind == "single":
        return _layout_single(spec, rng)
    if spec.kind in ("pallet", "partial"):
        return _layout_pallet(spec, rng, partial=spec.kind == "partial")
    if spec.kind == "mixed":
        return _layout_mixed(spec, rng)
    if spec.kind == "touching":
        return _layout_touching(spec, rng)
    if spec.kind == "layered":
        # Zero gaps and no jitter: neighbours touch along whole faces, layer on layer.
        layers = spec.layers if spec.layers is not None else int(rng.integers(2, 4))
        return _layout_pallet(dataclasses.replace(spec, max_gap=0.0, jitter=0.0, yaw_jitter=0.0,
                                                  layers=layers), rng, partial=False)
    return np.zeros((0, 7))


# --- decorations: tape and labels on the lids --------------------------------------------------

_TAPE, _LABEL = 0, 1
#: Diffuse reflectivity of each material: cardboard, tape, label, pallet wood, concrete floor.
_RHO_BOX, _RHO_TAPE, _RHO_LABEL, _RHO_PALLET, _RHO_FLOOR = 0.45, 0.35, 0.8, 0.4, 0.25


def _decorations(spec: SceneSpec, boxes: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Tape strips and labels on the lids that nothing rests on, (D, 9): slab (cx, cy, cz,
    sx, sy, sz, yaw) in the base frame, host box, material (0 tape, 1 label).

    Tape runs along the lid's long axis near its centre line, 48-75 mm wide (at most 0.4 of
    the short side) and 1-3 mm thick, stopping short of the bevels; a label is 70-120 x
    100-160 mm, 0.5-2 mm thick, anywhere on the lid it fits. Every box draws the same
    numbers whether it gets them or not, so one box's draw never shifts another's.
    """
    out = []
    free = ~_rests_on(boxes)
    for i, b in enumerate(boxes):
        u = rng.random(2)
        t_w, t_th = rng.uniform(0.048, 0.075), rng.uniform(0.001, 0.003)
        t_off = rng.uniform(-1, 1)
        l_w, l_l = rng.uniform(0.07, 0.12), rng.uniform(0.10, 0.16)
        l_th = rng.uniform(0.0005, 0.002)
        l_pos = rng.uniform(-1, 1, 2)
        if not free[i]:
            continue
        cx, cy, cz, sx, sy, sz, yaw = b
        top = cz + sz / 2
        along_x = sx >= sy
        long_, short = (sx, sy) if along_x else (sy, sx)
        rot = _rot_z(yaw)
        inner = 2 * spec.bevel + 0.004
        if u[0] < spec.tape:
            w = min(t_w, 0.4 * short)
            off = t_off * max(0.0, min(0.02, (short - w) / 2 - inner))
            local = np.array([0.0, off]) if along_x else np.array([off, 0.0])
            size = (long_ - inner, w) if along_x else (w, long_ - inner)
            xy = b[:2] + rot @ local
            out.append([xy[0], xy[1], top + t_th / 2, *size, t_th, yaw, i, _TAPE])
        if u[1] < spec.labels:
            room = np.array([sx, sy]) - inner - np.array([l_l, l_w] if along_x else [l_w, l_l])
            if (room > 0).all():
                local = l_pos * room / 2
                size = (l_l, l_w) if along_x else (l_w, l_l)
                xy = b[:2] + rot @ local
                out.append([xy[0], xy[1], top + l_th / 2, *size, l_th, yaw, i, _LABEL])
    return np.asarray(out, dtype=np.float64).reshape(-1, 9)


# --- the sensor pose -----------------------------------------------------------------------------


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


# --- the world in the sensor frame ---------------------------------------------------------------


@dataclass(frozen=True)
class _World:
    """Every object as half-spaces ``n . X <= d`` in the sensor frame.

    ``planes`` (O, K, 4) rows (n, d): boxes 0..B-1 (+x, -x, +y, -y, top, bottom, then the
    bevels of the +x, -x, +y, -y top edges), the decorations (tape, labels) B..B+D-1, the
    pallet P = B+D, the floor P+1 (its top only). ``host`` (O,): the box of each box or
    decoration (-1 for the pallet and the floor); ``lift`` (O,): a decoration's thickness;
    ``material`` (O,): 0 tape, 1 label, -1 else.
    ``verts`` (P+1, 8, 3): nominal corners, for culling. ``top_*``: each box's top-centre
    and local axes, for the bulge. ``n_rows`` (B+1,): real rows of each solid (the rest is
    padding). ``z_max`` (B+1,): top of each solid in the base frame; ``up`` (3,) and ``c_z``
    give a sensor-frame point's base height ``up . X + c_z``.
    """

    planes: np.ndarray
    verts: np.ndarray
    top_c: np.ndarray
    top_x: np.ndarray
    top_y: np.ndarray
    top_z: np.ndarray
    half: np.ndarray
    n_boxes: int
    bulge: float
    n_rows: np.ndarray
    z_max: np.ndarray
    up: np.ndarray
    c_z: float
    n_deco: int
    host: np.ndarray
    lift: np.ndarray
    material: np.ndarray

    @property
    def flat_planes(self) -> np.ndarray:
        return self.planes.reshape(-1, 4)

    @property
    def floor(self) -> int:
        """Object index of the floor."""
        return self.n_boxes + self.n_deco + 1


def _box_halfspaces(box: np.ndarray, bevel: float) -> np.ndarray:
    """(K, 4) half-spaces of a box with 45-degree bevels of size ``bevel`` on its top edges."""
    cx, cy, cz, sx, sy, sz, yaw = box
    ex = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    ey = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    ez = np.array([0.0, 0.0, 1.0])
    c = np.array([cx, cy, cz])
    hx, hy, hz = sx / 2, sy / 2, sz / 2
    rows = np.zeros((_K, 4))
    rows[:, 3] = 1.0  # padding: 0 . X <= 1 always holds
    for k, (n, h) in enumerate(((ex, hx), (-ex, hx), (ey, hy), (-ey, hy), (ez, hz), (-ez, hz))):
        rows[k] = [*n, n @ c + h]
    if bevel > 0:
        for k, (e, h) in enumerate(((ex, hx), (-ex, hx), (ey, hy), (-ey, hy))):
            n = (e + ez) / math.sqrt(2)
            rows[6 + k] = [*n, n @ c + (h + hz - bevel) / math.sqrt(2)]
    return rows


def _box_verts(box: np.ndarray) -> np.ndarray:
    c = _footprint_corners(box)
    lo, hi = box[2] - box[5] / 2, box[2] + box[5] / 2
    return np.concatenate([np.c_[c, np.full(4, lo)], np.c_[c, np.full(4, hi)]])


def _build_world(boxes: np.ndarray, T: np.ndarray, bevel: float, bulge: float,
                 deco: np.ndarray | None = None, pallet_on: bool = True) -> _World:
    """The scene in the sensor frame; ``deco`` (D, 9): decoration slabs (box columns, host,
    material); ``pallet_on`` False leaves the pallet out (it is never hit)."""
    R, C = T[:3, :3], T[:3, 3]
    B = len(boxes)
    dec = np.zeros((0, 9)) if deco is None else deco
    D = len(dec)
    P = B + D
    pallet = np.array([0.0, 0.0, _PALLET_TOP / 2, *PALLET_SIZE, 0.0])
    planes = np.zeros((P + 2, _K, 4))
    planes[:, :, 3] = 1.0
    for i, b in enumerate(boxes):
        planes[i] = _box_halfspaces(b, bevel)
    for j, dj in enumerate(dec):
        planes[B + j] = _box_halfspaces(dj[:7], 0.0)
    planes[P] = _box_halfspaces(pallet, 0.0)
    planes[P + 1, _TOP] = [0.0, 0.0, 1.0, 0.0]  # the floor: z <= 0
    # Base half-space n.X_b <= d with X_b = R X_s + C becomes (R^T n).X_s <= d - n.C.
    n_s = planes[..., :3] @ R
    d_s = planes[..., 3] - planes[..., :3] @ C
    pad = (planes[..., :3] == 0).all(-1)
    planes = np.concatenate([n_s, d_s[..., None]], -1)
    planes[pad] = [0.0, 0.0, 0.0, 1.0]
    verts = np.stack([_box_verts(b) for b in [*boxes, *dec[:, :7], pallet]])
    verts = (verts - C) @ R
    yaw = boxes[:, 6] if B else np.zeros(0)
    ex = np.stack([np.cos(yaw), np.sin(yaw), np.zeros(B)], 1)
    ey = np.stack([-np.sin(yaw), np.cos(yaw), np.zeros(B)], 1)
    ez = np.tile([0.0, 0.0, 1.0], (B, 1))
    top = boxes[:, :3] + np.c_[np.zeros((B, 2)), boxes[:, 5] / 2] if B else np.zeros((0, 3))
    n_rows = np.full(P + 1, _K if bevel > 0 else 6)
    n_rows[B:] = 6
    z_max = np.concatenate([boxes[:, 2] + boxes[:, 5] / 2 if B else np.zeros(0),
                            dec[:, 2] + dec[:, 5] / 2,
                            [_PALLET_TOP if pallet_on else -np.inf]])
    host = np.concatenate([np.arange(B), dec[:, 7].astype(np.int64), [-1, -1]])
    lift = np.concatenate([np.zeros(B), dec[:, 5], [0.0, 0.0]])
    material = np.concatenate([np.full(B, -1), dec[:, 8].astype(np.int64), [-1, -1]])
    return _World(planes=planes, verts=verts, top_c=(top - C) @ R, top_x=ex @ R, top_y=ey @ R,
                  top_z=ez @ R, half=boxes[:, 3:5] / 2 if B else np.zeros((0, 2)),
                  n_boxes=B, bulge=bulge, n_rows=n_rows, z_max=z_max, up=R[2].copy(),
                  c_z=float(C[2]), n_deco=D, host=host, lift=lift,
                  material=material)


# --- ray casting ---------------------------------------------------------------------------------


class _RayIndex:
    """Finds the rays whose direction falls in an image-plane box, by tiles of the image."""

    def __init__(self, D: np.ndarray, shape: tuple[int, int] | None) -> None:
        with np.errstate(divide="ignore", invalid="ignore"):
            a, b = D[:, 0] / D[:, 2], D[:, 1] / D[:, 2]
        ok = (D[:, 2] > 0) & np.isfinite(a) & np.isfinite(b)
        self.a, self.b = np.where(ok, a, np.nan), np.where(ok, b, np.nan)
        self.ok = ok
        self.tiles: np.ndarray | None = None
        if shape is not None:
            H, W = shape
            th, tw = -(-H // _TILE), -(-W // _TILE)
            idx = np.full((th * _TILE, tw * _TILE), -1, np.int64)
            idx[:H, :W] = np.arange(H * W).reshape(H, W)
            tiles = idx.reshape(th, _TILE, tw, _TILE).transpose(0, 2, 1, 3).reshape(th * tw, -1)
            valid = tiles >= 0
            valid[valid] = ok[tiles[valid]]
            ta = np.where(valid, a[np.maximum(tiles, 0)], np.nan)
            tb = np.where(valid, b[np.maximum(tiles, 0)], np.nan)
            self.amin = np.where(valid, ta, np.inf).min(1)
            self.amax = np.where(valid, ta, -np.inf).max(1)
            self.bmin = np.where(valid, tb, np.inf).min(1)
            self.bmax = np.where(valid, tb, -np.inf).max(1)
            self.tiles = tiles
        for v in vars(self).values():  # shared through the camera cache: never modified
            if isinstance(v, np.ndarray):
                v.flags.writeable = False

    def candidates(self, bbox: tuple[float, float, float, float] | None) -> np.ndarray:
        """Flat indices of the rays inside ``bbox`` = (a0, a1, b0, b1); all rays for None."""
        if bbox is None:
            return np.flatnonzero(self.ok)
        a0, a1, b0, b1 = bbox
        if self.tiles is not None:
            sel = (self.amax >= a0) & (self.amin <= a1) & (self.bmax >= b0) & (self.bmin <= b1)
            idx = self.tiles[sel].ravel()
            idx = idx[idx >= 0]
        else:
            idx = np.flatnonzero(self.ok)
        a, b = self.a[idx], self.b[idx]
        return idx[(a >= a0) & (a <= a1) & (b >= b0) & (b <= b1)]


def _bbox(verts: np.ndarray, O: np.ndarray) -> tuple[float, float, float, float] | None:
    """Image-plane box (x/z, y/z) of an object seen from ``O``; None if it reaches behind."""
    rel = verts - O
    if (rel[:, 2] <= 1e-6).any():
        return None
    a, b = rel[:, 0] / rel[:, 2], rel[:, 1] / rel[:, 2]
    eps = 1e-9
    return float(a.min() - eps), float(a.max() + eps), float(b.min() - eps), float(b.max() + eps)


def _cast(world: _World, O: np.ndarray, D: np.ndarray, index: _RayIndex, *,
          floor: bool = True, t_max: np.ndarray | None = None,
          normals: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Cast rays ``O + t D`` (``D`` (N, 3) unit, sensor frame) at the world.

    Parameters
    ----------
    t_max : (N,) float64, optional
        Only hits nearer than this count (default: any).
    normals : bool
        Also return the normals.

    Returns
    -------
    t : (N,) float64
        Distance to the first hit, metres; inf (or ``t_max``) for none.
    surf : (N,) int64
        ``object * K + half-space`` of the hit surface, -1 for none.
    normal : (N, 3) float64 or None
        Outward unit normal at the hit (bulge included), NaN for none.

    Notes
    -----
    Solids are visited from the highest top down. A ray going down (in the base frame) whose
    best hit so far is above a solid's top cannot meet that solid any nearer, so it is not
    tested: lower layers and the pallet cost only the rays that pass between the boxes above.
    """
    N = D.shape[0]
    best = np.full(N, np.inf) if t_max is None else np.array(t_max, dtype=np.float64)
    surf = np.full(N, -1, np.int64)
    DT = np.ascontiguousarray(D.T)
    dz = world.up @ DT  # base-frame vertical component of each ray
    down = dz < 0
    oz = float(world.up @ O) + world.c_z
    with np.errstate(invalid="ignore"):
        h_best = np.where(down, oz + best * dz, -np.inf)  # base height of the best hit
    h_best[np.isnan(h_best)] = -np.inf
    for o in np.argsort(-world.z_max, kind="stable"):
        cand = index.candidates(_bbox(world.verts[o], O))
        # A ray whose best hit is at or above this solid's top meets it no nearer.
        cand = cand[h_best[cand] < world.z_max[o] - 1e-9]
        if cand.size == 0:
            continue
        pl = world.planes[o, : world.n_rows[o]]
        dn = pl[:, :3] @ DT[:, cand]  # (k, M): rows are contiguous, reductions run along them
        num = pl[:, 3] - pl[:, :3] @ O
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num[:, None] / dn
        zero = dn == 0
        if zero.any():  # parallel to a face: outside it never inside (-inf), inside unbounded
            t[zero] = np.where(np.broadcast_to(num[:, None], t.shape)[zero] < 0, -np.inf, np.inf)
        M = cand.size
        t_in, t_out = np.full(M, -np.inf), np.full(M, np.inf)
        k = np.zeros(M, np.int64)
        for row in range(dn.shape[0]):
            tr, enter = t[row], dn[row] < 0
            upd = enter & (tr > t_in)
            np.copyto(t_in, tr, where=upd)
            k[upd] = row
            np.minimum(t_out, np.where(enter, np.inf, tr), out=t_out)
        hit = (t_in <= t_out) & (t_in > 1e-9) & (t_in < best[cand])
        sel = cand[hit]
        best[sel] = t_in[hit]
        surf[sel] = o * _K + k[hit]
        h_best[sel] = np.where(down[sel], oz + t_in[hit] * dz[sel], -np.inf)
    if floor:
        fl = world.floor
        n, d = world.planes[fl, _TOP, :3], world.planes[fl, _TOP, 3]
        idx = np.flatnonzero(down & (h_best < -1e-9) & index.ok)
        dn = n @ DT[:, idx]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (d - n @ O) / dn
        hit = (dn < 0) & (t > 1e-9) & (t < best[idx])
        best[idx[hit]] = t[hit]
        surf[idx[hit]] = fl * _K + _TOP
    if not normals:
        return best, surf, None
    # Row -1 (no hit) of the table is NaN.
    table = np.vstack([world.flat_planes[:, :3], np.full((1, 3), np.nan)])
    normal = np.take(table, surf, axis=0)
    if world.bulge > 0 and world.n_boxes:
        _bulge(world, O, D, best, surf, normal)
    return best, surf, normal


def _bulge(world: _World, O: np.ndarray, D: np.ndarray, t: np.ndarray, surf: np.ndarray,
           normal: np.ndarray) -> None:
    """Move top-face hits onto the bulged surface z = bulge (1-(u/hx)^2)(1-(v/hy)^2), in place
    (a decoration's top follows its lid's bulge, raised by its thickness)."""
    host = np.where(surf >= 0, world.host[np.maximum(surf, 0) // _K], -1)
    idx = np.flatnonzero((host >= 0) & (surf % _K == _TOP))
    if idx.size == 0:
        return
    lift = world.lift[surf[idx] // _K]
    o = host[idx]
    c, ex, ey, ez = world.top_c[o], world.top_x[o], world.top_y[o], world.top_z[o]
    hx, hy = world.half[o, 0], world.half[o, 1]
    d = D[idx]
    q0 = O - c
    z0, dz = (q0 * ez).sum(1), (d * ez).sum(1)
    ti = t[idx]
    for _ in range(5):  # a contraction: the bulge's slope is small
        p = q0 + ti[:, None] * d
        u, v = (p * ex).sum(1), (p * ey).sum(1)
        fu, fv = 1 - (u / hx) ** 2, 1 - (v / hy) ** 2
        h = world.bulge * np.maximum(fu, 0) * np.maximum(fv, 0) + lift
        ti = (h - z0) / dz
    p = q0 + ti[:, None] * d
    u, v = (p * ex).sum(1), (p * ey).sum(1)
    fu, fv = 1 - (u / hx) ** 2, 1 - (v / hy) ** 2
    inside = (fu > 0) & (fv > 0)
    gu = np.where(inside, world.bulge * (-2 * u / hx**2) * fv, 0.0)
    gv = np.where(inside, world.bulge * (-2 * v / hy**2) * fu, 0.0)
    n = ez - gu[:, None] * ex - gv[:, None] * ey
    t[idx] = ti
    normal[idx] = n / np.linalg.norm(n, axis=1, keepdims=True)


# --- ground truth --------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Faces:
    centers: np.ndarray
    normals: np.ndarray
    x_axis: np.ndarray
    y_axis: np.ndarray
    width: np.ndarray
    length: np.ndarray
    corners: np.ndarray


def _faces(boxes: np.ndarray, T: np.ndarray) -> _Faces:
    """The nominal top rectangle of every box, in the sensor frame."""
    R, C = T[:3, :3], T[:3, 3]
    B = len(boxes)
    yaw = boxes[:, 6]
    ex = np.stack([np.cos(yaw), np.sin(yaw), np.zeros(B)], 1)
    ey = np.stack([-np.sin(yaw), np.cos(yaw), np.zeros(B)], 1)
    swap = boxes[:, 3] > boxes[:, 4]
    x_b = np.where(swap[:, None], ey, ex)  # the width runs along the shorter side
    w = np.minimum(boxes[:, 3], boxes[:, 4])
    l = np.maximum(boxes[:, 3], boxes[:, 4])
    c_b = boxes[:, :3] + np.c_[np.zeros((B, 2)), boxes[:, 5] / 2]
    c = (c_b - C) @ R
    n = np.tile(np.array([0.0, 0.0, 1.0]) @ R, (B, 1))
    x = x_b @ R
    away = (n * -c).sum(1) < 0  # the sensor is below the face: the normal must face it
    n[away] *= -1
    y = np.cross(n, x)
    c0 = c - x * w[:, None] / 2 - y * l[:, None] / 2
    corners = np.stack([c0, c0 + x * w[:, None], c0 + x * w[:, None] + y * l[:, None],
                        c0 + y * l[:, None]], 1)
    return _Faces(c, n, x, y, w, l, corners.reshape(B, 4, 3))


def _visible_fraction(faces: _Faces, face_ids: np.ndarray, seen: np.ndarray,
                      rays: np.ndarray, f: float) -> np.ndarray:
    """Sum of the seeing pixels' footprints on each face plane over the face area, (F,)."""
    F = len(faces.width)
    if F == 0:
        return np.zeros(0)
    sel = (face_ids >= 0) & seen
    fid = face_ids[sel]
    u = rays[sel]
    n, c = faces.normals[fid], faces.centers[fid]
    nu = np.abs((n * u).sum(1))
    r = np.abs((n * c).sum(1)) / nu
    # Pixel solid angle u_z^3 / f^2, projected on the plane at range r.
    area = r**2 * u[:, 2] ** 3 / (f * f * nu)
    sums = np.bincount(fid, weights=area, minlength=F)
    return np.clip(sums / (faces.width * faces.length), 0.0, 1.0)


def _edge_pairs(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices (p, q) of every horizontal and vertical pair of neighbouring pixels."""
    H, W = shape
    idx = np.arange(H * W).reshape(H, W)
    p = np.concatenate([idx[:, :-1].ravel(), idx[:-1, :].ravel()])
    q = np.concatenate([idx[:, 1:].ravel(), idx[1:, :].ravel()])
    return p, q


def _edge_labels(world: _World, rays: np.ndarray, r0: np.ndarray, surf: np.ndarray,
                 shape: tuple[int, int], bevel: float) -> tuple[np.ndarray, np.ndarray]:
    """Edge labels of the noise-free render, and the pixels on either side of a jump.

    Two neighbouring pixels on different surfaces are a *crease* when the surfaces meet
    between them: the same (convex) box, or two objects whose planes meet, along the rays
    between the two pixels, within ``_CONTACT_TOL + bevel`` of both. Otherwise, or when one
    pixel sees nothing, they are a *jump*. A jump is labelled on the nearer pixel, a crease on
    the pixel nearer the meeting line.

    Returns
    -------
    labels : (H, W) uint8
    at_jump : (H, W) bool
        Both pixels of every jump pair (where mixed pixels happen).
    """
    p, q = _edge_pairs(shape)
    d = surf[p] != surf[q]
    p, q = p[d], q[d]
    sp, sq = surf[p], surf[q]
    vp, vq = sp >= 0, sq >= 0
    crease = np.zeros(p.size, bool)
    s_star = np.full(p.size, 0.5)
    both = vp & vq
    bi = np.flatnonzero(both)
    if bi.size:
        pl = world.flat_planes
        A, Bp = pl[sp[bi]], pl[sq[bi]]
        up, uq = rays[p[bi]], rays[q[bi]]
        # Along w(s) = (1-s) u_p + s u_q the planes are at lam = d / (n . w); they meet where
        # d_A (n_B . w) = d_B (n_A . w), linear in s.
        al0 = A[:, 3] * (Bp[:, :3] * up).sum(1) - Bp[:, 3] * (A[:, :3] * up).sum(1)
        al1 = A[:, 3] * (Bp[:, :3] * uq).sum(1) - Bp[:, 3] * (A[:, :3] * uq).sum(1)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            s = al0 / (al0 - al1)
            w = (1 - s)[:, None] * up + s[:, None] * uq
            lam = A[:, 3] / (A[:, :3] * w).sum(1)
            X = lam[:, None] * w
        X[~np.isfinite(X).all(1)] = 0.0  # no meeting point; rejected by the s and lam tests
        tol = _CONTACT_TOL + bevel
        oa, ob = sp[bi] // _K, sq[bi] // _K
        inside_a = (np.einsum("mkj,mj->mk", world.planes[oa, :, :3], X)
                    - world.planes[oa, :, 3]).max(1) <= tol
        inside_b = (np.einsum("mkj,mj->mk", world.planes[ob, :, :3], X)
                    - world.planes[ob, :, 3]).max(1) <= tol
        meet = (np.isfinite(s) & (s >= -0.5) & (s <= 1.5) & np.isfinite(lam) & (lam > 0)
                & inside_a & inside_b)
        coplanar = ((np.abs(A[:, :3] - Bp[:, :3]).max(1) < 1e-9)
                    & (np.abs(A[:, 3] - Bp[:, 3]) <= tol))
        same_obj = oa == ob
        crease[bi] = same_obj | meet | coplanar
        s_star[bi] = np.where(meet & np.isfinite(s), np.clip(s, 0, 1), 0.5)
    jump = ~crease & (vp | vq)
    near_p = np.where(both, r0[p] <= r0[q], vp)
    labels = np.zeros(shape[0] * shape[1], np.uint8)
    c_pix = np.where(s_star[crease] < 0.5, p[crease], q[crease])
    labels[c_pix] = 2
    j_pix = np.where(near_p[jump], p[jump], q[jump])
    labels[j_pix] = 1
    at_jump = np.zeros(shape[0] * shape[1], bool)
    at_jump[p[jump]] = True
    at_jump[q[jump]] = True
    return labels.reshape(shape), at_jump.reshape(shape)


# --- the sensor's artefacts ----------------------------------------------------------------------


def _shadowed(world: _World, X: np.ndarray, surf: np.ndarray, baseline: float, f: float,
              shape: tuple[int, int], everywhere: bool = False) -> np.ndarray:
    """Points (N, 3) that the emitter at (baseline, 0, 0) cannot see, (N,) bool.

    Notes
    -----
    The emitter sits on the sensor's x axis, so the occluder of a point at column u lies on
    the same image row at u + f b (1/z_occluder - 1/z_point) (depth z along the axis), where
    the camera sees another surface (or on a neighbouring row, for an occluder thinner than a
    pixel). Only pixels with a surface change that near on their right are cast (all of them
    with ``everywhere``, which the tests use to check this).
    """
    H, W = shape
    ok = np.isfinite(X).all(1)
    if baseline <= 0 or not ok.any():
        return np.zeros(X.shape[0], bool)
    if not everywhere:
        z = X[ok, 2]
        reach = int(math.ceil(f * baseline * (1.0 / z.min() - 1.0 / z.max()))) + 2
        s2 = surf.reshape(H, W)
        cols = np.broadcast_to(np.arange(W), (H, W))
        change = np.full((H, W), W)
        change[:, :-1] = np.where(s2[:, 1:] != s2[:, :-1], cols[:, :-1] + 1, W)
        nxt = np.minimum.accumulate(change[:, ::-1], axis=1)[:, ::-1]  # next change at or right
        # An occluder thinner than a pixel may show on a neighbouring row only.
        nxt[1:] = np.minimum(nxt[1:], nxt[:-1].copy())
        nxt[:-1] = np.minimum(nxt[:-1], nxt[1:].copy())
        ok &= ((nxt - cols) <= reach).ravel()
    idx = np.flatnonzero(ok)
    E = np.array([baseline, 0.0, 0.0])
    D = X[idx] - E
    dist = np.sqrt(np.einsum("ij,ij->i", D, D))
    D /= dist[:, None]
    index = _RayIndex(D, None) if idx.size < ok.size // 4 else _RayIndex(
        np.where(ok[:, None], X - E, np.nan), shape)
    if index.tiles is not None:  # many candidates: cast on the full grid, with its tiles
        full = np.full(X.shape, np.nan)
        full[idx] = D
        t_max = np.zeros(ok.size)
        t_max[idx] = dist - _SHADOW_EPS
        _, hit, _ = _cast(world, E, full, index, floor=False, t_max=t_max, normals=False)
        return ok & (hit >= 0)
    _, hit, _ = _cast(world, E, D, index, floor=False, t_max=dist - _SHADOW_EPS, normals=False)
    out = np.zeros(ok.size, bool)
    out[idx] = hit >= 0
    return out


def _supersampled_range(world: _World, pix: np.ndarray, sensor: PinholeModel) -> np.ndarray:
    """Mean range over a 2x2 grid of sub-pixel rays at each pixel (flat index), NaN if any miss."""
    v, u = np.divmod(pix, sensor.width)
    off = np.array([[-0.25, -0.25], [-0.25, 0.25], [0.25, -0.25], [0.25, 0.25]])
    uu = u[:, None] + off[None, :, 0]
    vv = v[:, None] + off[None, :, 1]
    d = np.stack([(uu - sensor.cx) / sensor.fx, (vv - sensor.cy) / sensor.fy,
                  np.ones_like(uu)], -1).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, _, _ = _cast(world, np.zeros(3), d, _RayIndex(d, None), normals=False)
    t = t.reshape(-1, 4)
    return np.where(np.isfinite(t).all(1), t.mean(1), np.nan)


def _measure(spec: SceneSpec, world: _World, sensor: PinholeModel, rays: np.ndarray,
             r0: np.ndarray, normal: np.ndarray, at_jump: np.ndarray, shadow: np.ndarray,
             rng: np.random.Generator) -> np.ndarray:
    """The noisy range image, (N,) float64 (NaN = no return), from the noise-free render."""
    N = r0.size
    # Draw every stream in full and in a fixed order, so options never shift other pixels.
    g = rng.standard_normal((2, N))
    z_range = rng.standard_normal(N)
    u_drop = rng.random(N)
    u_mixed = rng.random(N)
    hit = np.isfinite(r0)
    nu = np.where(hit, np.einsum("ij,ij->i", np.nan_to_num(normal), rays), -1.0)
    # Beam pointing jitter: a ray off by delta (perpendicular to it, sigma_angle per axis)
    # meets the hit's tangent plane at r0 (n.u) |u + delta| / (n.u + n.delta); n.delta only
    # sees the component along n's projection perpendicular to the ray.
    sa = spec.noise.sigma_angle
    n_perp = np.sqrt(np.maximum(1.0 - nu * nu, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        den = nu + sa * g[0] * n_perp * np.sign(nu)
        rj = r0 * nu * np.sqrt(1.0 + sa * sa * (g[0] ** 2 + g[1] ** 2)) / den
    r = np.where(hit & (np.abs(den) > 1e-6) & (rj > 0), rj, r0)
    if spec.mixed_pixels and spec.mixed_fraction > 0:
        pix = np.flatnonzero(at_jump.ravel() & (u_mixed < spec.mixed_fraction))
        if pix.size:
            rm = _supersampled_range(world, pix, sensor)
            good = np.isfinite(rm)
            r[pix[good]] = rm[good]
    sigma = spec.noise.sigma_range(np.where(hit, r0, 1.0), np.abs(nu))
    rho = spec.noise.row_corr
    if rho > 0:
        # an offset shared by each image row (drawn last, and only then: a model without
        # it renders the same scan as before it existed)
        z_row = rng.standard_normal(sensor.height)
        z_range = np.sqrt(1.0 - rho) * z_range + np.sqrt(rho) * z_row[np.arange(N) // sensor.width]
    r = r + z_range * sigma
    bad = ~hit | ~(r > 0) | (u_drop < spec.dropout)
    if spec.shadows:
        bad |= shadow
    return np.where(bad, np.nan, r)


# --- simulate ------------------------------------------------------------------------------------


def _streams(spec: SceneSpec) -> list[np.random.Generator]:
    """Independent generators for the layout, the pose, the default sensor's noise, the
    decorations and the zoo's sensor (spawned children are fixed by their index, so the first
    three are what they were when there were three)."""
    ss = np.random.SeedSequence([spec.seed, zlib.crc32(spec.kind.encode())])
    return [np.random.default_rng(s) for s in ss.spawn(5)]


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


@functools.lru_cache(maxsize=4)
def _camera(width: int, height: int, f: float) -> tuple[PinholeModel, np.ndarray, _RayIndex]:
    """The sensor model, its unit rays (N, 3) and their index (cached: scenes share them)."""
    sensor = PinholeModel(f, f, (width - 1) / 2, (height - 1) / 2, width, height)
    rays = sensor.rays().reshape(-1, 3)
    rays.flags.writeable = False
    return sensor, rays, _RayIndex(rays, (height, width))


def _render(spec: SceneSpec, boxes: np.ndarray, T: np.ndarray,
            streams: list[np.random.Generator]) -> SimulatedScan:
    H, W = spec.height, spec.width
    sensor, rays, index = _camera(W, H, float(spec.f))
    deco = _decorations(spec, boxes, streams[3]) if (spec.tape or spec.labels) else None
    world = _build_world(boxes, T, spec.bevel, spec.bulge, deco, spec.kind != "floor")
    r0, surf, normal = _cast(world, np.zeros(3), rays, index)
    r0 = np.where(np.isfinite(r0), r0, np.nan)
    # A decoration is part of its lid for the truth: its pixels see the host's top face.
    surf_t = _as_host_top(world, surf)
    labels, at_jump = _edge_labels(world, rays, r0, surf_t, (H, W), spec.bevel)
    B = len(boxes)
    obj, k = surf_t // _K, surf_t % _K
    face_ids = np.where((surf_t >= 0) & (obj < B) & np.isin(k, _FACE_PLANES), obj, -1)
    shadow = (_shadowed(world, r0[:, None] * rays, surf, spec.baseline, spec.f, (H, W))
              if spec.shadows and spec.sensor is None else np.zeros(H * W, bool))
    faces = _faces(boxes, T)
    seen = np.isfinite(r0)
    vis = _visible_fraction(faces, face_ids, seen, rays, spec.f)
    exposed = ~_rests_on(boxes) & (vis >= _FULLY_SEEN)
    truth = GroundTruth(
        centers=faces.centers, normals=faces.normals, x_axis=faces.x_axis, y_axis=faces.y_axis,
        width=faces.width, length=faces.length, corners=faces.corners, visible_fraction=vis,
        fully_exposed=exposed, box_index=np.arange(B, dtype=np.int32),
        face_ids=face_ids.reshape(H, W), edge_labels=labels, boxes=boxes, sensor_to_base=T,
    )
    if spec.sensor is None:
        assert normal is not None
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


def _as_host_top(world: _World, surf: np.ndarray) -> np.ndarray:
    """``surf`` with every decoration hit replaced by its host box's top face."""
    if world.n_deco == 0:
        return surf
    o = surf // _K
    deco = (surf >= 0) & (o >= world.n_boxes) & (o < world.n_boxes + world.n_deco)
    return np.where(deco, world.host[np.maximum(o, 0)] * _K + _TOP, surf)


def _concave_pixels(world: _World, rays: np.ndarray, r0: np.ndarray, surf: np.ndarray,
                    shape: tuple[int, int], f: float) -> np.ndarray:
    """Pixels on an inside corner, (N,) bool: two neighbours on different surfaces, each
    outside the other's half-space by > 1 mm, and close in space (a crease, not a jump)."""
    p, q = _edge_pairs(shape)
    sel = (surf[p] != surf[q]) & (surf[p] >= 0) & (surf[q] >= 0)
    p, q = p[sel], q[sel]
    X = r0[:, None] * rays
    A, Bp = world.flat_planes[surf[p]], world.flat_planes[surf[q]]
    out_a = (A[:, :3] * X[q]).sum(1) - A[:, 3]
    out_b = (Bp[:, :3] * X[p]).sum(1) - Bp[:, 3]
    close = np.linalg.norm(X[p] - X[q], axis=1) < 0.01 + 3 * r0[p] / f
    c = (out_a > 1e-3) & (out_b > 1e-3) & close
    m = np.zeros(r0.size, bool)
    m[p[c]] = True
    m[q[c]] = True
    return m


def _rendered(spec: SceneSpec, world: _World, sensor: PinholeModel, rays: np.ndarray,
              r0: np.ndarray, surf: np.ndarray, surf_t: np.ndarray, normal: np.ndarray | None,
              at_jump: np.ndarray) -> Rendered:
    """What a zoo sensor measures: the render with its materials and callbacks."""
    H, W = spec.height, spec.width
    assert normal is not None
    B, D = world.n_boxes, world.n_deco
    rho_obj = np.full(B + D + 3, _RHO_BOX)
    shiny_obj = np.zeros(B + D + 3, bool)
    tape = world.material[: B + D + 2] == _TAPE
    rho_obj[: B + D + 2][tape] = _RHO_TAPE
    rho_obj[: B + D + 2][world.material[: B + D + 2] == _LABEL] = _RHO_LABEL
    shiny_obj[: B + D + 2][tape] = True
    rho_obj[B + D], rho_obj[B + D + 1], rho_obj[-1] = _RHO_PALLET, _RHO_FLOOR, 0.0

    def per_pixel(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        o = np.where(s >= 0, s // _K, -1)
        return rho_obj[o], shiny_obj[o]

    rho, shiny = per_pixel(surf)
    cos_i = np.abs(np.einsum("ij,ij->i", normal, rays))
    X = r0[:, None] * rays

    def shadow(baseline: float) -> np.ndarray:
        return _shadowed(world, X, surf, baseline, spec.f, (H, W))

    def footprint(pix: np.ndarray, off: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        v, u = np.divmod(pix, W)
        uu = u[:, None] + off[None, :, 0]
        vv = v[:, None] + off[None, :, 1]
        d = np.stack([(uu - sensor.cx) / sensor.fx, (vv - sensor.cy) / sensor.fy,
                      np.ones_like(uu)], -1).reshape(-1, 3)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        t, s, n = _cast(world, np.zeros(3), d, _RayIndex(d, None))
        assert n is not None
        c = np.abs(np.einsum("ij,ij->i", np.nan_to_num(n), d))
        rr, _ = per_pixel(s)
        shape = (pix.size, off.shape[0])
        return (np.where(np.isfinite(t), t, np.nan).reshape(shape), c.reshape(shape),
                rr.reshape(shape))

    return Rendered(shape=(H, W), f=float(spec.f), rays=rays, r0=r0, cos_i=cos_i,
                    reflectivity=rho, shiny=shiny, at_jump=at_jump.ravel(),
                    concave=_concave_pixels(world, rays, r0, surf_t, (H, W), spec.f),
                    shadow=shadow, footprint=footprint)


# --- the benchmark suite -------------------------------------------------------------------------


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
    specs = []
    for i in range(int(n)):
        sensor = SENSORS[i % len(SENSORS)]
        kind = MATRIX_KINDS[(i // len(SENSORS)) % len(MATRIX_KINDS)]
        distance = round(float(rng.uniform(1.0, 3.5)), 3)
        tilt = round(float(rng.uniform(0.0, math.radians(30.0))), 4)
        w, h = _MATRIX_SIZES[int(rng.integers(len(_MATRIX_SIZES)))]
        sharp, bevel = rng.random() < 1 / 3, round(float(rng.uniform(0.0005, 0.005)), 4)
        bulge = round(float(rng.uniform(0.003, 0.015)), 4) if rng.random() < 0.4 else 0.0
        deco = rng.random() < 0.5
        scene_seed = int(rng.integers(0, 2**31))
        specs.append(SceneSpec(
            kind=kind, seed=scene_seed, width=w, height=h,
            f=round(_MATRIX_F640[sensor] * w / 640, 3), distance=distance, tilt=tilt,
            bevel=0.0 if (sharp or kind == "layered") else bevel, bulge=bulge, sensor=sensor,
            tape=0.6 if deco else 0.0, labels=0.5 if deco else 0.0))
    return specs


# --- files ---------------------------------------------------------------------------------------

_TRUTH = "truth/"


def save_npz(sim: SimulatedScan, path: str | os.PathLike[str]) -> None:
    """Write a simulated scan and its truth to ``path`` (written as given), atomically.

    Keys: ``points`` (H, W, 3) float32, ``intrinsics`` (3, 3), ``range`` (H, W) float32,
    ``sensor_to_base`` (4, 4), ``capture_time_ns`` 0-d int64, ``spec`` (JSON string) and
    ``truth/<field>`` for every :class:`GroundTruth` field. The scan keys are the public
    layout :func:`boxloc.io.read_scan` reads. The same scan always gives the same bytes.
    """
    if not isinstance(sim, SimulatedScan):
        raise TypeError(f"sim must be a SimulatedScan, got {type(sim).__name__}")
    scan = sim.scan
    assert isinstance(scan.sensor, PinholeModel)
    arrays: dict[str, np.ndarray] = {
        "points": np.ascontiguousarray(scan.points, dtype=np.float32),
        "intrinsics": scan.sensor.K,
        "range": np.ascontiguousarray(scan.range, dtype=np.float32),
        "sensor_to_base": np.asarray(scan.sensor_to_base, dtype=np.float64),
        "capture_time_ns": np.asarray(scan.capture_time_ns, dtype=np.int64),
        "spec": np.asarray(json.dumps(sim.spec.to_dict(), sort_keys=True, separators=_JSON_SEP)),
    }
    arrays.update(to_arrays(sim.truth, prefix=_TRUTH))
    from boxloc.io import write_arrays_npz  # io reads scans; it does not need the simulator

    write_arrays_npz(path, arrays)


def load_truth(path: str | os.PathLike[str]) -> GroundTruth | None:
    """The ground truth stored in an ``.npz`` by :func:`save_npz`; None if it has none.

    Raises
    ------
    InputError
        The file is missing, not an ``.npz``, or its truth is incomplete or corrupt.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"scan file not found: {p}")
    try:
        with np.load(p, allow_pickle=False) as z:
            arrays = {k[len(_TRUTH):]: z[k] for k in z.files if k.startswith(_TRUTH)}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as e:
        raise InputError(f"{p}: cannot read the .npz: {str(e).splitlines()[0]}") from None
    if not arrays:
        return None
    try:
        return from_arrays(GroundTruth, arrays)
    except KeyError as e:
        raise InputError(f"{p}: incomplete ground truth: {e.args[0]}") from None
    except (ValueError, TypeError) as e:
        raise InputError(f"{p}: bad ground truth: {str(e).splitlines()[0]}") from None


def output_paths(out: str | os.PathLike[str], spec: SceneSpec, seeds: list[int],
                 numbered: bool) -> list[Path]:
    """Where ``boxloc simulate`` writes each scan.

    An existing directory (or a path ending in a separator) gets ``KIND_SEED.npz`` files;
    otherwise ``numbered`` gives ``STEM_000.npz``, ``STEM_001.npz``... next to ``out``, and a
    single scan goes to ``out`` itself (``.npz`` appended if missing).
    """
    text = os.fspath(out)
    p = Path(text)
    if p.is_dir() or text.endswith(("/", os.sep)):
        return [p / f"{spec.kind}_{s:04d}.npz" for s in seeds]
    stem = p.name[:-4] if p.name.endswith(".npz") else p.name
    if numbered:
        return [p.with_name(f"{stem}_{i:03d}.npz") for i in range(len(seeds))]
    return [p.with_name(stem + ".npz")]


def simulate_to_files(spec: SceneSpec | str, out: str | os.PathLike[str],
                      seed: int | None = None,
                      count: int | None = None) -> Iterator[tuple[Path, SimulatedScan]]:
    """Simulate ``count`` scans (seeds ``seed``, ``seed + 1``...) and save each as ``.npz``.

    Yields ``(path, sim)`` after each file is written (paths from :func:`output_paths`).

    Raises
    ------
    InputError
        A bad spec, a count < 1, or an output directory that does not exist.
    """
    if isinstance(spec, str):
        spec = parse_spec(spec)
    if count is not None and (isinstance(count, bool) or count < 1):
        raise InputError(f"count must be >= 1, got {count}")
    base = spec.seed if seed is None else seed
    if isinstance(base, bool) or not isinstance(base, int) or base < 0:
        raise InputError(f"seed must be an integer >= 0, got {base!r}")
    seeds = [base + i for i in range(count or 1)]
    paths = output_paths(out, spec, seeds, numbered=count is not None)
    parent = paths[0].parent
    if os.fspath(out).endswith(("/", os.sep)):
        parent.mkdir(parents=True, exist_ok=True)
    if not parent.is_dir():
        raise InputError(f"output directory does not exist: {parent}")
    for path, s in zip(paths, seeds):
        sim = simulate(spec, seed=s)
        save_npz(sim, path)
        yield path, sim


def summary_line(path: str | os.PathLike[str], sim: SimulatedScan) -> str:
    """One line about a saved scan: boxes, faces, graspable faces, sensor distance and tilt."""
    t = sim.truth
    sp = sim.spec
    return (f"{os.fspath(path)}: {sp.kind} seed={sp.seed} boxes={t.boxes.shape[0]} "
            f"faces={len(t)} graspable={int(t.fully_exposed.sum())} "
            f"distance={sp.distance:.2f}m tilt={math.degrees(sp.tilt or 0.0):.1f}deg"
            + (f" sensor={sp.sensor}" + (f"/{sp.sensor_class}" if sp.sensor_class else "")
               + f" noise_scale={sp.noise_scale:g}" if sp.sensor else ""))

"""The scene specification: what to simulate, and its one-line text form.

:class:`SceneSpec` holds every knob of a scene (its kind, the seed, the camera, the noise, the
box sizes, the sensor); :func:`parse_spec` reads ``KIND[:key=value,...]`` and
:func:`format_spec` writes it back, so ``parse_spec(format_spec(s)) == s``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from boxloc.errors import InputError
from boxloc.scan import NoiseModel
from boxloc.simulate.zoo import SENSORS, STEREO_CLASSES

__all__ = ["KINDS", "PATTERNS", "SceneSpec", "parse_spec", "override_spec", "format_spec"]

KINDS = ("single", "pallet", "partial", "mixed", "touching", "empty", "layered", "floor")
#: How a ``layered`` scene lays its cartons within a layer: every carton the same way
#: (``grid``), or interlocked (``weave``: cartons twice as long as wide, in square cells of
#: two, each cell turned at random, and one column of single cartons, so the layer has the
#: outline of a grid of the carton and is not one).
PATTERNS = ("grid", "weave")


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
    pattern : str
        One of :data:`PATTERNS`, how a ``layered`` scene's layers are laid (``grid`` for
        every other kind). ``weave`` draws the carton's short edge in [min_edge,
        max_edge / 2] and its long edge twice that, so it needs max_edge >= 2 min_edge.
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
    pattern: str = "grid"

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
        check("pattern", self.pattern in PATTERNS, "one of " + ", ".join(PATTERNS))
        if self.pattern != "grid":
            check("pattern", self.kind == "layered", "grid unless the kind is layered")
            check("pattern", self.max_edge >= 2 * self.min_edge,
                  f"grid unless max_edge >= 2 min_edge (cartons of a {self.pattern} are "
                  "twice as long as wide)")

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
                               "tape": 0.0, "labels": 0.0, "pattern": "grid"}


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

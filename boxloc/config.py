"""The localizer's configuration: one significance level, the probability of success, the
sensor noise model and a few named priors. Nothing else is tunable, by design (paper §2.2:
"all thresholds can be replaced by a unique value, the significance level").
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import tomllib
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from boxloc.errors import InputError
from boxloc.scan import NoiseModel

#: Keys that logs written before every value was recorded left out, with the value their
#: run used. Frozen: these are facts about old logs, not defaults. A key added to the
#: config later must be added here with the value that reproduces what a run before it did,
#: so that logs written without it keep saying (and replaying) what they ran.
UNRECORDED_KEYS: dict[str, Any] = {
    "noise_auto": False,
    "trial_seed": 0,
    "end_tolerance": 0.75,
    "noise.edge_px": 0.0,
    "noise.row_corr": 0.0,
    "noise.incidence_exponent": 1.0,
    "noise.corr_px_rows": 0.0,
    "noise.corr_px_cols": 0.0,
    # logs before the exposure test measured its null on the scan's flat tiles
    "noise.exceed_rate": 0.0,
    "noise.exceed_dispersion": 1.0,
    # logs before the exposure test widened a core's count by its tiles' correlation
    "noise.exceed_corr_px": 0.0,
    "max_line_work": 0,
    "max_vertices": 0,
    "max_hypothesis_work": 0,
    # logs before issue #21 knew no carton list; their tolerance was never used
    "box_sizes": (),
    "size_tolerance": 0.01,
    # logs before the density-free MDL counted raw points (issue #20 part 2)
    "mdl_face_points": 0.0,
    # logs before the edge stage's budget (issue #22 part 2) ran every scan line
    "max_edge_work": 0,
    # logs before hole_weight counted a face's holes as points off its plane, and needed
    # no share of its pixels to return
    "hole_weight": 1.0,
    "min_return_fraction": 0.0,
}

#: The noise terms ``noise_auto`` estimates from each scan; giving any of them pins the model.
ESTIMATED_NOISE_TERMS = frozenset({"sigma0", "k1", "k2", "row_corr", "incidence_exponent",
                                   "corr_px_rows", "corr_px_cols", "exceed_rate",
                                   "exceed_dispersion", "exceed_corr_px"})

#: Config fields that change how a result is computed, never what it is.
EXECUTION_FIELDS = frozenset({"workers"})


def _normalise_box_sizes(rows: Any) -> tuple[tuple[float, float, float], ...]:
    """``Config.box_sizes`` as a tuple of (width, length, height) floats, width <= length,
    an unknown height as :data:`math.nan` (one object, so equal configs compare equal).

    Accepts rows of two (no height) or three numbers; a height of None or NaN is unknown.
    """
    if not isinstance(rows, list | tuple):
        raise InputError(f"config box_sizes must be a list of [width, length(, height)] "
                         f"rows, got {rows!r:.80}")
    out = []
    for i, row in enumerate(rows):
        if not isinstance(row, list | tuple) or len(row) not in (2, 3):
            raise InputError(f"config box_sizes row {i} must be [width, length] or [width, "
                             f"length, height], got {row!r:.80}")
        vals = []
        for j, v in enumerate(row):
            if j == 2 and (v is None or (isinstance(v, float) and math.isnan(v))):
                vals.append(math.nan)
                continue
            if isinstance(v, bool) or not isinstance(v, int | float) or not (
                    math.isfinite(v) and v > 0):
                raise InputError(f"config box_sizes row {i} must hold positive finite "
                                 f"metres, got {row!r:.80}")
            vals.append(float(v))
        w, ln = sorted(vals[:2])
        out.append((w, ln, vals[2] if len(vals) == 3 else math.nan))
    return tuple(out)


@dataclass(frozen=True)
class Config:
    """Parameters of :func:`boxloc.pipeline.find_graspable_surfaces`.

    Parameters
    ----------
    alpha : float
        Significance level of every statistical test (Förstner, Brunn & Heuel 2000).
    p_success : float
        Probability of detecting the shortest line (Olson 2001); the paper uses 0.9.
    noise : NoiseModel
        Range-noise model of the sensor; every test's covariance comes from it. With
        ``noise_auto`` its range terms are only the fallback for a scan with too little
        flat surface; ``sigma_angle``, ``min_cos`` and ``edge_px`` are always used.
    noise_auto : bool
        Estimate each scan's range noise (``sigma0``, ``k1``, ``k2``, ``row_corr``) from its
        own flat regions before the edge stage (:mod:`boxloc.stages.scan_noise`; the estimate is
        the scan's ``noise`` product), so a sensor nobody calibrated gets tests at their
        level. A config file or ``--set`` that gives any of those terms without
        ``noise_auto`` pins the model (``noise_auto = false``); pinned, the scan's
        residuals are still tested against the model (NOISE_FIT).
    min_edge, max_edge : float
        Prior: shortest and longest box edge, metres. The shortest edge sets the smallest
        line worth finding (and so the number of Hough trials); the longest bounds the
        dimension searches, and keeps a bare pallet (1.2 m) from passing for a box.
    max_tilt : float
        Prior: largest angle between a graspable surface's normal and "up", radians.
    min_crease_angle : float
        Prior: smallest fold between two box faces, radians. Smaller folds (cardboard bulge)
        are not crease edges.
    support_fraction : float
        The paper's threshold p, as a fraction of the far-side perimeter that edge points
        must cover in ``dimensions_from_edges``.
    min_inlier_fraction : float
        Prior: the fraction of the range points inside a fully exposed face that lie on its
        plane (the rest are noise, bulge and mixed pixels at its border). Verification's
        continuation test uses it too: a strip beyond a side with this fraction on the
        face's plane is more of the same face. Counted over the pixels that returned:
        holes (dark labels, tape, dropouts) are no evidence against a face.
    min_return_fraction : float
        Prior: the fraction of the pixels inside a face that must return a range for its
        points to verify it (verification's ``VERIFY_INLIERS`` row 1). Active-stereo and
        time-of-flight sensors return nothing from dark labels and tape: on the
        development scenes up to two fifths of a box top's pixels were holes. 0: no such
        requirement (logs written before this key).
    hole_weight : float
        How much a pixel inside a face that returned nothing counts against it in
        ``VERIFY_INLIERS``: 0, not at all (a hole is no evidence of anything off the
        plane); 1, as a point off the plane (logs written before this key).
    flatness : float
        Prior: how far a box top may depart from a plane (cardboard bulge), metres; added
        in quadrature to the point noise when points are tested against a face, and to
        the distance of two lines in the meet test.
    angle_tolerance : float
        Prior: how far real box edges depart from square and straight (cardboard, and a
        line that runs along the edges of several neighbouring boxes), radians; added in
        quadrature to the direction uncertainty in the orthogonal and parallel tests.
    end_tolerance : float
        Prior: how far the two lines of a vertex may meet beyond the end of either segment,
        as a fraction of ``min_edge``. Near a junction both scan directions cross the edge
        badly, so support thins out, and real boxes' corners are rounded, dented or
        chamfered by flaps: on the mOSD Kinect frames segments stop 18-26 mm short of a
        top's corner (``min_edge`` 35 mm). Much more joins a segment to the far side of its
        neighbour in a dense layer.
    mdl_k1, mdl_k2, mdl_k3 : float
        MDL weights (Leonardis et al.): per explained point, per unit of normalized squared
        residual, per model parameter.
    mdl_face_points : float
        The MDL's model cost in faces, not pixels: one parameter costs ``mdl_k3 /
        mdl_face_points`` of the points a face of the smallest box (``min_edge`` square)
        has at the candidate's place (its pixels per square metre times ``min_edge``^2),
        1 % at the defaults, so the selection does not depend on the resolution or the
        distance. 0 charges ``mdl_k3`` raw points per parameter, as Leonardis and logs
        before this key did.
    workers : int
        Processes for the per-vertex stage (1 = serial; results are identical).
    max_pixels : int
        Largest scan accepted, pixels; larger scans are refused before any work.
    direction_granularity : int
        Subdivision level of the icosahedral direction accumulator (4 gives 1281 cells).
    max_edge_work : int
        Budget of the edge stage: samples its split-and-merge may visit in all (each
        split's chord distances, each merge's fit), half for the rows and the rest for the
        columns. No scan line is started once it is spent: the lines after it get no
        edges, and a BUDGET row records it. A scan needs 5-27 per pixel (seed-2 matrix
        draw, 24 scans; the most 3.3e7, a 1280x960 active-stereo pile), pure noise under
        a pinned model 43-45 per pixel (1.4e8 at 2048x1536, 8-9 s: 50-65 ns each, the
        rest of the stage included). The default, 4.5x the most an ordinary scan needs,
        holds the stage to about 10 s on the largest scan accepted. 0: no budget.
    max_line_work : int
        Budget of the line stage: neighbour points its Hough trials may examine in all
        (each trial examines the live edge points within its vote radius; about 4 us
        each). Ordinary scans need up to ~2e5 (mOSD frames, simulated piles); a scan of
        noise edges needed 2e7 (77 s). At the budget (5x the most an ordinary scan needs)
        the stage stops with the lines found and records a BUDGET row. 0: no budget.
    max_vertices : int
        Budget of the hypothesis stage: vertices whose rectangles are searched and
        verified (~20-50 ms each), the highest first; ordinary scans have up to ~25. 0: no
        budget.
    max_hypothesis_work : int
        Budget of the hypothesis stage's work: pixels its rectangle searches may read in
        all (each verified attempt its rectangle's, each extent its strip's, each seam
        search its region's, as projected into the image; reading range points is what
        takes its time, about 0.25-0.5 us a pixel). Under it the work is done most valuable
        first: each round's search for box tops, the highest vertices first, then the
        flat regions (never surfaces); a vertex's search is done whole or not at all. At
        the budget the stage stops with what it found and records a BUDGET row. On two
        development draws of the matrix bench (160 scans each) the 99th percentile read
        5.1e6 and 6.2e6 (1280x960 piles), the most 1.1e7 (4 s); 4 of the 320 reach this
        budget, and lost no box top found without it. Measured again at 213abc7 (matrix
        draws of seeds 1 and 2, 256 scans): 11 reach it, all 960x720 or 1280x960 at
        about a metre, reading up to 4.3e7 without it (12.8 s, 0.3 us a pixel); two of
        them lose tops (a structured-light pallet 8 of 12, a laser pile 1 of 2). A budget
        of 20 reads per image pixel would have kept the pallet's (1.8e7) but let a
        1280x960 scan read 2.5e7, about 7 s at that rate: past the matrix bench's bound
        of ten times the median scan (issue 22). 0: no budget.
    trial_seed : int
        Which stream of random trials to draw (the Hough trials' distinguished points and
        voters, the up estimate's and the baseline's RANSAC): 0, the default, seeds them
        from the scan's content alone (:attr:`boxloc.scan.Scan.seed`); k > 0 from the scan
        and k (:meth:`seed_for`). Running k = 0, 1, 2, ... measures how much a result owes
        to the draw (``boxloc bench --seeds N``, also with ``--real``).
    box_sizes : tuple of (width, length, height)
        Prior: the carton sizes the cell handles (its SKU list), metres, ``width <=
        length`` (normalised), ``height`` NaN where unknown; ``()``, the default, is no list
        (``boxloc locate --box-sizes FILE``, :func:`boxloc.io.box_sizes.read_box_sizes`).
        With a list, a rectangle's dimensions are tested against it (SKU_SIZE), a flat
        region that is a multiple of a listed size is split at the implied seams, and a
        reported box that matches none is flagged. In a file it is a list of ``[width,
        length]`` or ``[width, length, height]`` rows.
    size_tolerance : float
        Prior: the 1-sigma tolerance of a listed size, metres. A carton's nominal
        dimensions and its rectangle as measured differ by the cardboard's manufacturing
        tolerance (a few mm), its bulged walls, and the edge and seam localization (one
        pixel is 2-6 mm at 1-3 m for a 525 px focal length); 10 mm covers them together.
    """

    alpha: float = 0.01
    p_success: float = 0.9
    noise: NoiseModel = field(default_factory=NoiseModel)
    noise_auto: bool = True
    min_edge: float = 0.10
    max_edge: float = 1.00
    max_tilt: float = math.radians(45.0)
    min_crease_angle: float = math.radians(20.0)
    support_fraction: float = 0.3
    min_inlier_fraction: float = 0.8
    min_return_fraction: float = 0.5
    hole_weight: float = 0.0
    flatness: float = 0.005
    angle_tolerance: float = math.radians(1.0)
    # 1/2 lost corners of the mOSD tops in some draws of the trials, 1 lost faces of the
    # simulated neat layers
    end_tolerance: float = 0.75
    mdl_k1: float = 1.0
    mdl_k2: float = 0.5
    mdl_k3: float = 10.0
    mdl_face_points: float = 1000.0
    workers: int = 1
    max_pixels: int = 16_777_216
    direction_granularity: int = 4
    max_edge_work: int = 150_000_000
    max_line_work: int = 1_000_000
    max_vertices: int = 500
    max_hypothesis_work: int = 6_000_000
    trial_seed: int = 0
    box_sizes: tuple[tuple[float, float, float], ...] = ()
    size_tolerance: float = 0.01

    def __post_init__(self) -> None:
        def check(name: str, ok: bool, what: str) -> None:
            if not ok:
                raise InputError(f"config {name} must be {what}, got {getattr(self, name)!r}")

        check("alpha", 0 < self.alpha < 0.5, "in (0, 0.5)")
        check("p_success", 0 < self.p_success < 1, "in (0, 1)")
        check("min_edge", 0 < self.min_edge < self.max_edge, "> 0 and < max_edge")
        check("max_edge", math.isfinite(self.max_edge), "finite")
        check("max_tilt", 0 < self.max_tilt <= math.pi / 2, "in (0, pi/2]")
        check("min_crease_angle", 0 < self.min_crease_angle < math.pi / 2, "in (0, pi/2)")
        check("support_fraction", 0 < self.support_fraction <= 1, "in (0, 1]")
        check("min_inlier_fraction", 0 < self.min_inlier_fraction <= 1, "in (0, 1]")
        check("min_return_fraction", 0 <= self.min_return_fraction <= 1, "in [0, 1]")
        check("hole_weight", 0 <= self.hole_weight <= 1, "in [0, 1]")
        check("flatness", 0 <= self.flatness < 0.1, "in [0, 0.1) m")
        check("angle_tolerance", 0 <= self.angle_tolerance < 0.2, "in [0, 0.2) rad")
        check("end_tolerance", 0 <= self.end_tolerance <= 1, "in [0, 1] (of min_edge)")
        for k in ("mdl_k1", "mdl_k2", "mdl_k3", "mdl_face_points"):
            check(k, math.isfinite(getattr(self, k)) and getattr(self, k) >= 0, "finite and >= 0")
        check("workers", isinstance(self.workers, int) and self.workers >= 1, "an integer >= 1")
        check("max_pixels", isinstance(self.max_pixels, int) and self.max_pixels > 0, "> 0")
        for k in ("max_edge_work", "max_line_work", "max_vertices", "max_hypothesis_work"):
            v = getattr(self, k)
            check(k, isinstance(v, int) and not isinstance(v, bool) and v >= 0,
                  "an integer >= 0 (0: no budget)")
        check("direction_granularity", self.direction_granularity in range(2, 7), "in 2..6")
        check("trial_seed", isinstance(self.trial_seed, int) and not isinstance(
            self.trial_seed, bool) and 0 <= self.trial_seed < 2**63, "an integer >= 0")
        check("noise_auto", isinstance(self.noise_auto, bool), "true or false")
        check("size_tolerance", isinstance(self.size_tolerance, int | float)
              and not isinstance(self.size_tolerance, bool)
              and 0 < self.size_tolerance < 0.1, "in (0, 0.1) m")
        object.__setattr__(self, "box_sizes", _normalise_box_sizes(self.box_sizes))
        if not isinstance(self.noise, NoiseModel):
            raise TypeError(f"config noise must be a NoiseModel, got {type(self.noise)}")

    # --- serialization -------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        """Every value, defaults included (what a log records: its provenance is complete)."""
        d = dataclasses.asdict(self)
        d["noise"] = self.noise.to_dict()
        # TOML and JSON have no NaN-safe null: an unknown height is a row of two
        d["box_sizes"] = [[w, ln] if math.isnan(h) else [w, ln, h]
                          for w, ln, h in self.box_sizes]
        return d

    def seed_for(self, scan_seed: int) -> int:
        """The seed of the random trials on a scan whose content seed is ``scan_seed``.

        ``trial_seed`` 0 gives ``scan_seed`` itself; k > 0 a 63-bit hash of both, so every
        (scan, k) has its own stream and the same pair always the same one.
        """
        if self.trial_seed == 0:
            return int(scan_seed)
        h = hashlib.blake2b(digest_size=8)
        h.update(np.asarray([scan_seed, self.trial_seed], dtype=np.uint64).tobytes())
        return int.from_bytes(h.digest(), "little") >> 1

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Config:
        if not isinstance(d, dict):
            raise InputError(f"config must be a table of key = value, got {type(d).__name__}")
        d = dict(d)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise InputError(f"unknown config key(s): {', '.join(unknown)}")
        noise = d.pop("noise", None)
        if isinstance(noise, dict) and "noise_auto" not in d and (
                ESTIMATED_NOISE_TERMS & set(noise)):
            d["noise_auto"] = False  # a noise model given (calibrate-noise's file) pins it
        kw: dict[str, Any] = {}
        if noise is not None:
            if isinstance(noise, NoiseModel):
                kw["noise"] = noise
            elif not isinstance(noise, dict):
                raise InputError(f"config noise must be a table, got {noise!r:.80}")
            else:
                nk = {f.name for f in dataclasses.fields(NoiseModel)}
                bad = sorted(str(k) for k in set(noise) - nk)
                if bad:
                    names = ", ".join("noise." + b for b in bad)
                    raise InputError(f"unknown config key(s): {names}")
                for k, v in noise.items():
                    if isinstance(v, bool) or not isinstance(v, int | float):
                        raise InputError(f"config noise.{k} must be a number, got {v!r:.80}")
                kw["noise"] = NoiseModel(**{k: float(v) for k, v in noise.items()})
        for k, v in d.items():
            default = getattr(cls, k, None)
            if isinstance(default, int) and not isinstance(default, bool):
                if isinstance(v, float) and v.is_integer():
                    v = int(v)
                if not isinstance(v, int):
                    raise InputError(f"config {k} must be an integer, got {v!r}")
            elif k == "box_sizes":
                pass  # checked by _normalise_box_sizes
            elif isinstance(default, float):
                if not isinstance(v, int | float) or isinstance(v, bool):
                    raise InputError(f"config {k} must be a number, got {v!r}")
                v = float(v)
            kw[k] = v
        return cls(**kw)

    @classmethod
    def from_recorded(cls, d: dict[str, Any]) -> Config:
        """The config a log recorded.

        Logs written before every value was recorded (``to_dict`` then left out
        :data:`UNRECORDED_KEYS` at their defaults) get those keys from that frozen table,
        never from today's defaults: a default changed later changes neither what an old
        log says nor what its replay runs. Any other missing key is an error, as nothing
        says what the run used.
        """
        if not isinstance(d, dict):
            raise InputError(f"config must be a table of key = value, got {type(d).__name__}")
        d = dict(d)
        noise = d.get("noise")
        if isinstance(noise, dict):
            d["noise"] = noise = dict(noise)
        for key, value in UNRECORDED_KEYS.items():
            head, _, tail = key.partition(".")
            if not tail:
                d.setdefault(head, value)
            elif isinstance(noise, dict):
                noise.setdefault(tail, value)
        required = {f.name for f in dataclasses.fields(cls)}
        missing = sorted(required - set(d))
        if isinstance(noise, dict):
            missing += sorted("noise." + f.name for f in dataclasses.fields(NoiseModel)
                              if f.name not in noise)
        if missing:
            raise InputError(f"recorded config lacks {', '.join(missing)}")
        return cls.from_dict(d)

    def canonical_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"))

    @property
    def hash(self) -> str:
        """SHA-256 (first 16 hex digits) of the canonical JSON of the fields that can change
        a result.

        Execution settings (``workers``) are left out, as results never depend on them, and
        so are :data:`UNRECORDED_KEYS` at their table values: a config hashes as it did when
        logs left those keys out, so old logs' hashes still name the same configs.
        """
        d = {k: v for k, v in self.to_dict().items() if k not in EXECUTION_FIELDS}
        for key, value in UNRECORDED_KEYS.items():
            head, _, tail = key.partition(".")
            table, name = (d[head], tail) if tail else (d, head)
            v = table.get(name, value)
            if v == value or (isinstance(v, list | tuple) and isinstance(value, list | tuple)
                              and list(v) == list(value)):
                table.pop(name, None)
        text = json.dumps(d, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def to_toml(self) -> str:
        """Every parameter as TOML (``boxloc config``)."""
        return tomli_w.dumps(self.to_dict())

    @classmethod
    def from_toml(cls, text: str) -> Config:
        try:
            return cls.from_dict(tomllib.loads(text))
        except tomllib.TOMLDecodeError as e:
            raise InputError(f"config is not valid TOML: {e}") from None

    @classmethod
    def load(cls, path: str | Path) -> Config:
        p = Path(path)
        if not p.is_file():
            raise InputError(f"config file not found: {p}")
        return cls.from_toml(p.read_text())

    def with_overrides(self, assignments: list[str] | dict[str, Any]) -> Config:
        """Apply ``key=value`` overrides; dotted keys reach into ``noise``.

        Values are parsed as TOML scalars (``alpha=0.05``, ``workers=2``). Setting a noise
        term that ``noise_auto`` estimates (``noise.k2=0.001``) pins the model unless
        ``noise_auto`` is set too.
        """
        d = self.to_dict()
        items: Iterable[tuple[str, Any]]
        if isinstance(assignments, dict):
            items = assignments.items()
        else:
            parsed = []
            for a in assignments:
                if "=" not in a:
                    raise InputError(f"override must be key=value, got {a!r}")
                k, v = a.split("=", 1)
                try:
                    val = tomllib.loads(f"v = {v.strip()}")["v"]
                except tomllib.TOMLDecodeError:
                    raise InputError(f"override {k.strip()}: cannot parse value {v!r}") from None
                parsed.append((k.strip(), val))
            items = parsed
        items = list(items)
        keys = {k for k, _ in items}
        if "noise_auto" not in keys and any(
                k.startswith("noise.") and k[6:] in ESTIMATED_NOISE_TERMS for k in keys):
            d["noise_auto"] = False  # a noise term given pins the model
        for k, v in items:
            parts = k.split(".")
            tgt = d
            for p in parts[:-1]:
                if p not in tgt or not isinstance(tgt[p], dict):
                    raise InputError(f"unknown config key: {k}")
                tgt = tgt[p]
            if parts[-1] not in tgt:
                raise InputError(f"unknown config key: {k}")
            tgt[parts[-1]] = v
        return Config.from_dict(d)

"""Compare two runs of the localizer, scan by scan and stage by stage (after openpilot).

``diff_logs(base, candidate)`` reads two boxloc logs, matches their scans by sequence (the
scan index) and returns a :class:`LogDiff`: for every scan a :class:`ScanDiff` with

* ``identical``: the inputs and every stage's product are equal bit for bit (the fast path;
  wall-clock timing is never part of it);
* per-stage counts, base and candidate;
* item-by-item matches within tolerances: lines (end points, direction), vertices (point,
  both directions), hypotheses (generating vertex + rectangle) and their attempts;
* tests whose decision flipped: the same kind on matched entities, accepted in one run and
  rejected in the other;
* surfaces added, removed or moved (centre in mm, angle in degrees, width/length in mm),
  paired by an optimal assignment on centre distance, and changes of the pick order;
* scores where ground truth exists (:func:`boxloc.evaluate.metrics.match_surfaces`) and the fate of
  annotated picks (did the candidate change the surface whose pick failed?);
* timing per stage, on a channel of its own: it never counts as a difference.

Comparison returns data (a list of :class:`Difference` per scan); formatting is
:mod:`replay.report`'s. What counts as a regression lives in ``tolerances.toml``: every
:class:`Difference` names the rule that judges it, so :func:`regression` can re-judge a diff
under other tolerances.

Float comparisons: ``|a - b| > max(atol, rtol * max(|a|, |b|))`` (:func:`differs`).
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from boxloc.errors import BoxlocError, InputError, LogError
from boxloc.jsonable import jsonable as _jsonable
from boxloc.products import (
    OPTIONAL_STAGES,
    STAGES,
    AmbiguityReason,
    AmbiguousSet,
    DimensionSource,
    HeightSource,
    HypothesisSet,
    LineSet,
    SurfaceSet,
    VertexSet,
    products_equal,
)
from boxloc.stats import TestKind, TestTable

#: The key of the ambiguous regions in a scan record's products (and the stage of their
#: differences): they are part of the result, not a pipeline stage.
AMBIGUOUS = "ambiguous"
#: The stages whose tests are compared decision by decision (the edge stage's tests name
#: scan lines and breakpoints, which are compared through the edge map instead).
TEST_STAGES = ("lines", "vertices", "hypotheses", "verification", "surfaces")

_INFEASIBLE = 1e18
#: The default tolerances, every entry commented (shipped as package data).
DEFAULT_TOLERANCES = Path(__file__).with_name("tolerances.toml")


# --- tolerances ------------------------------------------------------------------------------


@dataclass(frozen=True)
class IgnoreTol:
    fields: tuple[str, ...] = ("timing_ms",)


@dataclass(frozen=True)
class MatchTol:
    line_endpoint_mm: float = 5.0
    line_endpoint_px: float = 2.0
    line_angle_deg: float = 1.0
    vertex_mm: float = 5.0
    vertex_px: float = 2.0
    vertex_angle_deg: float = 1.0
    hypothesis_dim_mm: float = 5.0
    hypothesis_rtol: float = 0.0


@dataclass(frozen=True)
class SurfaceTol:
    pair_gate_mm: float = 100.0
    center_mm: float = 3.0
    angle_deg: float = 1.0
    dim_mm: float = 3.0
    dim_rtol: float = 0.0
    pick_height_mm: float = 20.0
    height_mm: float = 5.0
    ambiguous_gate_mm: float = 100.0
    ambiguous_center_mm: float = 5.0
    ambiguous_dim_mm: float = 5.0


@dataclass(frozen=True)
class ScoreTol:
    truth: tuple[str, ...] = ("simulator", "npz")
    iou_min: float = 0.5
    max_normal_deg: float = 15.0
    max_plane_offset_mm: float = 30.0
    precision_drop: float = 0.0
    recall_drop: float = 0.0
    center_err_mm: float = 2.0
    dim_err_mm: float = 2.0


@dataclass(frozen=True)
class RegressionRules:
    surface_removed: bool = True
    surface_added: bool = True
    surface_moved: bool = True
    truth_decides: bool = True
    pick_order: bool = True
    tp_lost: bool = True
    fp_gained: bool = True
    error_grew: bool = True
    scan_failed: bool = True
    scan_missing: bool = True
    failed_pick_changed: bool = False
    failed_pick_unchanged: bool = False
    ok_pick_changed: bool = True
    stage_counts: bool = False
    flipped_tests: bool = False
    height_changed: bool = True
    sku_changed: bool = True
    ambiguous_added: bool = True
    ambiguous_removed: bool = True
    ambiguous_changed: bool = True


@dataclass(frozen=True)
class Tolerances:
    """The tolerances of a diff and its regression rules (see ``replay/tolerances.toml``)."""

    ignore: IgnoreTol = field(default_factory=IgnoreTol)
    match: MatchTol = field(default_factory=MatchTol)
    surfaces: SurfaceTol = field(default_factory=SurfaceTol)
    scores: ScoreTol = field(default_factory=ScoreTol)
    regression: RegressionRules = field(default_factory=RegressionRules)
    source: str = "defaults"

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        for sec in d.values():
            if isinstance(sec, dict):
                for k, v in sec.items():
                    if isinstance(v, tuple):
                        sec[k] = list(v)
        return d


_SECTIONS: dict[str, type] = {
    "ignore": IgnoreTol, "match": MatchTol, "surfaces": SurfaceTol, "scores": ScoreTol,
    "regression": RegressionRules,
}
_TRUTH_SOURCES = ("simulator", "npz")


def _read_toml(path: Path | None) -> dict[str, Any]:
    try:
        if path is None:
            text = DEFAULT_TOLERANCES.read_text("utf-8")
            where = str(DEFAULT_TOLERANCES)
        else:
            text = Path(path).read_text("utf-8")
            where = str(path)
    except FileNotFoundError:
        raise InputError(f"tolerances file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read tolerances file {path}: {e}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{where} is not valid TOML: {e}") from None


def _coerce(section: str, key: str, value: Any, default: Any) -> Any:
    name = f"{section}.{key}"
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise InputError(f"tolerance {name} must be true or false, got {value!r}")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(
                value) or value < 0:
            raise InputError(f"tolerance {name} must be a finite number >= 0, got {value!r}")
        return float(value)
    if isinstance(default, tuple):
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise InputError(f"tolerance {name} must be a list of strings, got {value!r}")
        if name == "scores.truth":
            bad = [v for v in value if v not in _TRUTH_SOURCES]
            if bad:
                raise InputError(f"tolerance scores.truth: unknown source(s) {bad}; expected "
                                 f"some of {list(_TRUTH_SOURCES)}")
        return tuple(value)
    raise AssertionError(name)  # pragma: no cover - every field has one of the types above


def _merge(tree: Mapping[str, Any], base: Tolerances | None, source: str) -> Tolerances:
    unknown = sorted(set(tree) - set(_SECTIONS))
    if unknown:
        raise InputError(f"unknown tolerance section(s): {', '.join(unknown)} (expected "
                         f"{', '.join(_SECTIONS)})")
    sections: dict[str, Any] = {}
    for sec, cls in _SECTIONS.items():
        current = getattr(base, sec) if base is not None else cls()
        given = tree.get(sec, {})
        if not isinstance(given, dict):
            raise InputError(f"tolerance section [{sec}] must be a table")
        names = {f.name for f in dataclasses.fields(cls)}
        bad = sorted(set(given) - names)
        if bad:
            raise InputError(f"unknown tolerance(s) in [{sec}]: {', '.join(bad)}")
        kw = {k: _coerce(sec, k, v, getattr(current, k)) for k, v in given.items()}
        sections[sec] = dataclasses.replace(current, **kw)
    return Tolerances(**sections, source=source)


def load_tolerances(path: str | os.PathLike[str] | None = None) -> Tolerances:
    """The tolerances: the defaults of ``replay/tolerances.toml``, overridden by ``path``.

    Raises
    ------
    InputError
        The file is missing or not TOML, or names a key the defaults do not have, or a
        value of the wrong type.
    """
    defaults = _merge(_read_toml(None), None, "defaults")
    if path is None:
        return defaults
    return _merge(_read_toml(Path(path)), defaults, str(path))


def differs(a: float, b: float, atol: float, rtol: float = 0.0) -> bool:
    """Whether ``|a - b| > max(atol, rtol * max(|a|, |b|))``; NaN equals only NaN."""
    fa, fb = float(a), float(b)
    if math.isnan(fa) or math.isnan(fb):
        return math.isnan(fa) != math.isnan(fb)
    return abs(fa - fb) > max(atol, rtol * max(abs(fa), abs(fb)))


# --- the result of a comparison --------------------------------------------------------------


@dataclass(frozen=True)
class Difference:
    """One difference between the baseline and the candidate.

    Attributes
    ----------
    scan : int or None
        The scan index; None for a difference of the whole log (pooled scores).
    stage : str
        ``scan``, a stage of :data:`boxloc.products.STAGES`, ``scores`` or ``picks``.
    kind : str
        What differs: ``count``, ``edge_map``, ``only_base``, ``only_candidate``,
        ``changed``, ``flipped``, ``surface_removed``, ``surface_added``, ``surface_moved``,
        ``pick_order``, ``tp_lost``, ``fp_gained``, ``error_grew``, ``score``,
        ``failed_pick``, ``ok_pick``, ``scan_failed``, ``scan_recovered``, ``scan_missing``,
        ``scan_extra``, ``height_changed``, ``sku_changed`` (stage ``surfaces``),
        ``ambiguous_added``, ``ambiguous_removed``, ``ambiguous_changed`` (stage
        ``ambiguous``).
    message : str
        One line for people.
    rule : str or None
        The ``[regression]`` rule (or ``[scores]`` threshold) that judges it; None: never a
        regression (reported only).
    values : dict
        The numbers behind it (JSON-ready).
    regression : bool
        The judgement under the tolerances the diff was made with.
    """

    scan: int | None
    stage: str
    kind: str
    message: str
    rule: str | None = None
    values: dict[str, Any] = field(default_factory=dict)
    regression: bool = False

    def to_json(self) -> dict[str, Any]:
        return {"scan": self.scan, "stage": self.stage, "kind": self.kind,
                "message": self.message, "rule": self.rule, "regression": self.regression,
                "values": _jsonable(self.values)}


def is_regression(d: Difference, tol: Tolerances) -> bool:
    """Judge one difference under ``tol`` (the rule it names, see ``tolerances.toml``)."""
    if d.rule is None:
        return False
    if d.rule in ("precision_drop", "recall_drop"):
        b, c = d.values.get("base"), d.values.get("candidate")
        if b is None or c is None:
            return False
        return float(b) - float(c) > getattr(tol.scores, d.rule) + 1e-12
    if d.rule in ("center_err_mm", "dim_err_mm"):
        b, c = d.values.get("base"), d.values.get("candidate")
        if c is None:
            return False
        if b is None:  # errors of true positives where there were none: nothing to compare
            return False
        return float(c) - float(b) > getattr(tol.scores, d.rule)
    return bool(getattr(tol.regression, d.rule))


@dataclass
class ItemMatch:
    """Items of one stage matched between the runs.

    ``pairs`` are (base id, candidate id); ``changed`` are pairs that match as entities but
    whose content differs beyond tolerance (hypotheses: the rectangle).
    """

    n_base: int
    n_candidate: int
    pairs: list[tuple[int, int]] = field(default_factory=list)
    only_base: list[int] = field(default_factory=list)
    only_candidate: list[int] = field(default_factory=list)
    changed: list[dict[str, Any]] = field(default_factory=list)

    def base_to_cand(self) -> dict[int, int]:
        return {b: c for b, c in self.pairs}

    def cand_to_base(self) -> dict[int, int]:
        return {c: b for b, c in self.pairs}

    @property
    def same(self) -> bool:
        return not (self.only_base or self.only_candidate or self.changed)

    def to_json(self) -> dict[str, Any]:
        return {"n_base": self.n_base, "n_candidate": self.n_candidate,
                "matched": len(self.pairs), "only_base": self.only_base,
                "only_candidate": self.only_candidate, "changed": _jsonable(self.changed)}


@dataclass(frozen=True)
class FlippedTest:
    """A test on matched entities whose decision differs between the runs."""

    stage: str
    kind: str
    base: dict[str, Any]
    candidate: dict[str, Any]

    def to_json(self) -> dict[str, Any]:
        return {"stage": self.stage, "kind": self.kind, "base": _jsonable(self.base),
                "candidate": _jsonable(self.candidate)}


@dataclass(frozen=True)
class SurfacePair:
    """A surface of the baseline paired with one of the candidate (by centre distance)."""

    base: int
    candidate: int
    dcenter_mm: float
    dnormal_deg: float
    dyaw_deg: float
    dwidth_mm: float
    dlength_mm: float
    pick_base: int
    pick_candidate: int
    moved: bool
    #: the box heights, mm (None: not measured), their sources, and whether they differ
    #: beyond ``[surfaces] height_mm`` or in source
    height_mm: tuple[float | None, float | None] = (None, None)
    height_source: tuple[str, str] = ("NONE", "NONE")
    height_changed: bool = False
    #: the matched carton sizes (-1: none) and flags of the two runs, and whether they differ
    sku: tuple[int, int] = (-1, -1)
    sku_flagged: tuple[bool, bool] = (False, False)
    sku_changed: bool = False

    @property
    def dangle_deg(self) -> float:
        return max(self.dnormal_deg, self.dyaw_deg)

    def to_json(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["dangle_deg"] = self.dangle_deg
        return _jsonable(d)


@dataclass
class SurfaceDiff:
    pairs: list[SurfacePair] = field(default_factory=list)
    removed: list[int] = field(default_factory=list)
    added: list[int] = field(default_factory=list)
    pick_order_base: list[int] = field(default_factory=list)
    pick_order_candidate: list[int] = field(default_factory=list)
    #: pairs (i, j) of baseline ids picked in the other order, with their height
    #: difference in mm (None without a known "up")
    swaps: list[tuple[int, int, float | None]] = field(default_factory=list)
    #: a swap between surfaces whose heights differ by more than pick_height_mm
    pick_order_significant: bool = False

    @property
    def moved(self) -> list[SurfacePair]:
        return [p for p in self.pairs if p.moved]

    @property
    def pick_order_changed(self) -> bool:
        return self.pick_order_base != self.pick_order_candidate

    def to_json(self) -> dict[str, Any]:
        return {"pairs": [p.to_json() for p in self.pairs], "removed": self.removed,
                "added": self.added, "moved": [p.base for p in self.moved],
                "pick_order_base": self.pick_order_base,
                "pick_order_candidate": self.pick_order_candidate,
                "pick_order_changed": self.pick_order_changed,
                "pick_order_significant": self.pick_order_significant,
                "swaps": _jsonable(self.swaps)}


@dataclass(frozen=True)
class AmbiguousPair:
    """An ambiguous region of the baseline paired with one of the candidate (by the
    distance of their outlines' centres)."""

    base: int
    candidate: int
    dcenter_mm: float
    dwidth_mm: float
    dlength_mm: float
    reason: tuple[str, str]
    changed: bool

    def to_json(self) -> dict[str, Any]:
        return _jsonable(dataclasses.asdict(self))


@dataclass
class AmbiguousDiff:
    """The ambiguous regions (``Result.ambiguous``) of two runs of one scan."""

    n_base: int = 0
    n_candidate: int = 0
    pairs: list[AmbiguousPair] = field(default_factory=list)
    removed: list[int] = field(default_factory=list)
    added: list[int] = field(default_factory=list)

    @property
    def changed(self) -> list[AmbiguousPair]:
        return [p for p in self.pairs if p.changed]

    def to_json(self) -> dict[str, Any]:
        return {"n_base": self.n_base, "n_candidate": self.n_candidate,
                "pairs": [p.to_json() for p in self.pairs], "removed": self.removed,
                "added": self.added, "changed": [p.base for p in self.changed]}


@dataclass
class ScanDiff:
    """The comparison of one scan (matched by sequence) of two logs.

    ``status`` is ``identical`` (bit for bit), ``equivalent`` (not bit for bit, but no
    difference beyond tolerance), ``changed``, ``missing`` (only in the baseline), ``extra``
    (only in the candidate) or ``error`` (the two records are not of the same input).
    """

    log: str
    scan: int
    status: str
    identical: bool = False
    error: str | None = None
    changed_fields: list[str] = field(default_factory=list)
    counts: dict[str, tuple[int | None, int | None]] = field(default_factory=dict)
    test_counts: dict[str, dict[str, list[int]]] = field(default_factory=dict)
    edge_pixels_changed: int = 0
    items: dict[str, ItemMatch] = field(default_factory=dict)
    flipped: list[FlippedTest] = field(default_factory=list)
    surfaces: SurfaceDiff = field(default_factory=SurfaceDiff)
    ambiguous: AmbiguousDiff = field(default_factory=AmbiguousDiff)
    scores: dict[str, Any] | None = None
    picks: list[dict[str, Any]] = field(default_factory=list)
    timing: dict[str, dict[str, float]] = field(default_factory=dict)
    failures: dict[str, Any] = field(default_factory=dict)
    differences: list[Difference] = field(default_factory=list)

    @property
    def regression(self) -> bool:
        return any(d.regression for d in self.differences)

    def to_json(self) -> dict[str, Any]:
        return {
            "log": self.log, "scan": self.scan, "status": self.status,
            "identical": self.identical, "regression": self.regression, "error": self.error,
            "changed_fields": self.changed_fields,
            "counts": {k: list(v) for k, v in self.counts.items()},
            "test_counts": self.test_counts,
            "edge_pixels_changed": self.edge_pixels_changed,
            "items": {k: v.to_json() for k, v in self.items.items()},
            "flipped_tests": [f.to_json() for f in self.flipped],
            "surfaces": self.surfaces.to_json(),
            "ambiguous": self.ambiguous.to_json(),
            "scores": _jsonable(self.scores),
            "picks": _jsonable(self.picks),
            # wall clock, its own channel: never part of "differences"
            "timing_ms": _jsonable(self.timing),
            "failures": _jsonable(self.failures),
            "differences": [d.to_json() for d in self.differences],
        }


@dataclass
class LogDiff:
    """The comparison of two logs (or the same-named logs of two directories)."""

    base: Path
    candidate: Path
    tolerances: Tolerances
    scans: list[ScanDiff] = field(default_factory=list)
    error: str | None = None
    differences: list[Difference] = field(default_factory=list)
    pooled: dict[str, Any] | None = None
    config_changes: dict[str, list[Any]] = field(default_factory=dict)
    versions: dict[str, str] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.base.name

    @property
    def all_differences(self) -> list[Difference]:
        return [*self.differences, *(d for s in self.scans for d in s.differences)]

    @property
    def regression(self) -> bool:
        return any(d.regression for d in self.all_differences)

    @property
    def has_error(self) -> bool:
        return self.error is not None or any(s.status == "error" for s in self.scans)

    @property
    def identical(self) -> bool:
        return (not self.has_error and all(s.identical for s in self.scans)
                and not self.differences)


def regression(diff: LogDiff | ScanDiff | Iterable[LogDiff],
               tolerances: Tolerances | None = None) -> bool:
    """Whether a diff is a regression under ``tolerances`` (default: those it was made with).

    Every difference names the rule that judges it, so a diff can be re-judged under other
    rules without comparing the logs again (the *matching* tolerances are those of the diff).
    """
    if isinstance(diff, ScanDiff):
        if tolerances is None:
            return diff.regression
        return any(is_regression(d, tolerances) for d in diff.differences)
    diffs = [diff] if isinstance(diff, LogDiff) else list(diff)
    for ld in diffs:
        tol = tolerances or ld.tolerances
        if any(is_regression(d, tol) for d in ld.all_differences):
            return True
    return False


# --- helpers ---------------------------------------------------------------------------------


def _angle_deg(a: np.ndarray, b: np.ndarray, *, unsigned: bool = False) -> np.ndarray:
    """Angles between rows of unit vectors, degrees; ``unsigned``: of the lines (0..90)."""
    c = np.einsum("...k,...k->...", a, b)
    if unsigned:
        c = np.abs(c)
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def _assign(cost: np.ndarray) -> list[tuple[int, int]]:
    """Optimal one-to-one pairs of a cost matrix, leaving out infeasible ones."""
    if cost.size == 0:
        return []
    c = np.where(np.isfinite(cost), cost, _INFEASIBLE)
    rows, cols = linear_sum_assignment(c)
    return [(int(r), int(k)) for r, k in zip(rows, cols) if c[r, k] < _INFEASIBLE]


def _item_match(n_b: int, n_c: int, pairs: list[tuple[int, int]]) -> ItemMatch:
    pb = {b for b, _ in pairs}
    pc = {c for _, c in pairs}
    return ItemMatch(n_b, n_c, sorted(pairs), [i for i in range(n_b) if i not in pb],
                     [j for j in range(n_c) if j not in pc])


# --- item matching ---------------------------------------------------------------------------


def _gate_m(atol_mm: float, px: float, pixel_angle: float, r: np.ndarray) -> np.ndarray:
    """Per-item distance gate, metres: ``atol_mm``, or ``px`` pixels' footprint at the item's
    range ``r`` (metres) when larger (an end point moves by one edge point's spacing when the
    support gains or loses one, and that spacing is ``range * pixel_angle``)."""
    return np.maximum(atol_mm / 1e3, px * pixel_angle * np.nan_to_num(r))


def match_lines(a: LineSet, b: LineSet, tol: MatchTol, pixel_angle: float = 0.0) -> ItemMatch:
    """Lines whose end points (either orientation) and directions agree within ``tol``.

    Parameters
    ----------
    pixel_angle : float
        Radians per pixel of the scan (``scan.sensor.pixel_angle``), for the ``*_px`` gate.
    """
    na, nb = len(a), len(b)
    if na == 0 or nb == 0:
        return _item_match(na, nb, [])
    sa, ea, sb, eb = a.starts[:, None], a.ends[:, None], b.starts[None], b.ends[None]
    same = np.maximum(np.linalg.norm(sa - sb, axis=-1), np.linalg.norm(ea - eb, axis=-1))
    flip = np.maximum(np.linalg.norm(sa - eb, axis=-1), np.linalg.norm(ea - sb, axis=-1))
    d = np.minimum(same, flip)
    r = np.maximum(np.linalg.norm(a.starts, axis=1), np.linalg.norm(a.ends, axis=1))
    gate = _gate_m(tol.line_endpoint_mm, tol.line_endpoint_px, pixel_angle, r)
    ang = _angle_deg(a.directions[:, None], b.directions[None], unsigned=True)
    ok = (d <= gate[:, None]) & (ang <= tol.line_angle_deg)
    return _item_match(na, nb, _assign(np.where(ok, d, np.inf)))


def match_vertices(a: VertexSet, b: VertexSet, tol: MatchTol,
                   pixel_angle: float = 0.0) -> ItemMatch:
    """Vertices whose points and both directions (d1 with d1, d2 with d2) agree."""
    na, nb = len(a), len(b)
    if na == 0 or nb == 0:
        return _item_match(na, nb, [])
    d = np.linalg.norm(a.points[:, None] - b.points[None], axis=-1)
    gate = _gate_m(tol.vertex_mm, tol.vertex_px, pixel_angle, np.linalg.norm(a.points, axis=1))
    a1 = _angle_deg(a.d1[:, None], b.d1[None])
    a2 = _angle_deg(a.d2[:, None], b.d2[None])
    ok = (d <= gate[:, None]) & (a1 <= tol.vertex_angle_deg) & (a2 <= tol.vertex_angle_deg)
    return _item_match(na, nb, _assign(np.where(ok, d, np.inf)))


def _rect_differs(wa: float, la: float, wb: float, lb: float, tol: MatchTol) -> bool:
    return differs(wa * 1e3, wb * 1e3, tol.hypothesis_dim_mm, tol.hypothesis_rtol) or differs(
        la * 1e3, lb * 1e3, tol.hypothesis_dim_mm, tol.hypothesis_rtol)


def match_hypotheses(
    a: HypothesisSet, b: HypothesisSet, vertices: ItemMatch, tol: MatchTol
) -> tuple[ItemMatch, ItemMatch]:
    """Hypotheses by their generating vertex, then their rectangles; attempts likewise.

    Returns
    -------
    hypotheses : ItemMatch
        Pairs of hypotheses whose vertices match; ``changed`` lists those whose kept
        rectangle (source, width, length) differs beyond tolerance.
    attempts : ItemMatch
        Attempts of matched hypotheses paired in order by source, diagonal vertex (mapped)
        and dimensions within tolerance.
    """
    hyp_of_a = {int(v): h for h, v in enumerate(a.vertex)}
    hyp_of_b = {int(v): h for h, v in enumerate(b.vertex)}
    pairs: list[tuple[int, int]] = []
    for va, vb in vertices.pairs:
        if va in hyp_of_a and vb in hyp_of_b:
            pairs.append((hyp_of_a[va], hyp_of_b[vb]))
    hm = _item_match(len(a), len(b), pairs)
    vmap = vertices.base_to_cand()
    att_pairs: list[tuple[int, int]] = []
    atts_a = _attempts_by_hypothesis(a)
    atts_b = _attempts_by_hypothesis(b)
    for ha, hb in hm.pairs:
        wa, la, wb, lb = (float(a.width[ha]), float(a.length[ha]), float(b.width[hb]),
                          float(b.length[hb]))
        src_a, src_b = int(a.source[ha]), int(b.source[hb])
        if src_a != src_b or _rect_differs(wa, la, wb, lb, tol):
            hm.changed.append({
                "base": ha, "candidate": hb,
                "source": [DimensionSource(src_a).name, DimensionSource(src_b).name],
                "width_mm": [wa * 1e3, wb * 1e3], "length_mm": [la * 1e3, lb * 1e3]})
        free = list(atts_b.get(hb, []))
        for ja in atts_a.get(ha, []):
            for jb in free:
                if int(a.att_source[ja]) != int(b.att_source[jb]):
                    continue
                da, db = int(a.att_diagonal[ja]), int(b.att_diagonal[jb])
                if (da >= 0 or db >= 0) and vmap.get(da, -2) != db:
                    continue
                if _rect_differs(float(a.att_width[ja]), float(a.att_length[ja]),
                                 float(b.att_width[jb]), float(b.att_length[jb]), tol):
                    continue
                att_pairs.append((ja, jb))
                free.remove(jb)
                break
    am = _item_match(a.n_attempts, b.n_attempts, att_pairs)
    return hm, am


def _same_peaks(a: HypothesisSet, b: HypothesisSet, hyps: ItemMatch,
                tol: MatchTol) -> ItemMatch:
    """The matched hypotheses whose accumulator peaks (M_x and M_y) agree within tolerance."""

    def peaks(h: HypothesisSet, i: int) -> tuple[np.ndarray, np.ndarray]:
        return (h.peaks_x[h.peaks_x_offsets[i]:h.peaks_x_offsets[i + 1]],
                h.peaks_y[h.peaks_y_offsets[i]:h.peaks_y_offsets[i + 1]])

    pairs = []
    for ha, hb in hyps.pairs:
        (xa, ya), (xb, yb) = peaks(a, ha), peaks(b, hb)
        if xa.shape == xb.shape and ya.shape == yb.shape and not any(
                differs(p * 1e3, q * 1e3, tol.hypothesis_dim_mm, tol.hypothesis_rtol)
                for p, q in zip([*xa, *ya], [*xb, *yb])):
            pairs.append((ha, hb))
    return _item_match(hyps.n_base, hyps.n_candidate, pairs)


def _attempts_by_hypothesis(h: HypothesisSet) -> dict[int, list[int]]:
    out: dict[int, list[int]] = {}
    for j, hh in enumerate(h.att_hypothesis):
        out.setdefault(int(hh), []).append(j)
    return out


# --- tests whose decision flipped ------------------------------------------------------------


def _test_keys(t: TestTable, maps: Mapping[str, Mapping[int, int] | None]) -> dict[tuple, int]:
    """``{(kind, entities..., occurrence): row}`` with entity ids translated by ``maps``.

    ``maps[name]`` translates this run's ids into the baseline's (None: identity); a test
    on an entity without a counterpart gets no key (its entity is reported instead).
    """

    def m(name: str, i: int) -> int | None:
        mp = maps.get(name)
        return int(i) if mp is None else mp.get(int(i))

    out: dict[tuple, int] = {}
    seen: dict[tuple, int] = {}
    for r in range(len(t)):
        kind = int(t.kind[r])
        a, b = int(t.a[r]), int(t.b[r])
        key: tuple | None
        if kind in (TestKind.LINES_MEET, TestKind.LINES_ORTHOGONAL, TestKind.AT_SEGMENT_ENDS):
            x, y = m("lines", a), m("lines", b)
            key = None if x is None or y is None else (kind, min(x, y), max(x, y))
        elif kind == TestKind.POINT_ON_LINE:
            x = m("lines", a)
            key = None if x is None else (kind, x)
        elif kind in (TestKind.COPLANAR, TestKind.PARALLEL, TestKind.FIRST_QUADRANT):
            x, y = m("hypotheses", a), m("vertices", b)
            key = None if x is None or y is None else (kind, x, y)
        elif kind == TestKind.POINT_ON_PLANE:
            x = m("hypotheses", a)
            key = None if x is None else (kind, x)
        elif kind == TestKind.EDGE_SUPPORT:
            # one row per pair of accumulator peaks, in peak order: rows correspond only
            # between hypotheses whose peaks agree ("peaks": those pairs)
            x = m("peaks", a)
            key = None if x is None else (kind, x)
        elif (TestKind.VERIFY_INLIERS <= kind <= TestKind.VERIFY_SEAM_INTERIOR
              or kind in (TestKind.VERIFY_CONTINUATION, TestKind.VERIFY_SEAM_CROSSING,
                          TestKind.VERIFY_SEAM_IN_LINE, TestKind.VERIFY_RAISED_BEYOND,
                          TestKind.VERIFY_RAISED_HEIGHT, TestKind.VERIFY_SEAM_MIDLINE,
                          TestKind.SURFACE_BULGE, TestKind.REPEATS_NEIGHBOUR)):
            x = m("attempts", a)
            key = None if x is None else (kind, x)
        elif kind in (TestKind.SEAM_PEAK, TestKind.FACE_EXTENT, TestKind.SKU_ROW):
            x = m("hypotheses", a)
            key = None if x is None else (kind, x, b)
        elif kind == TestKind.BOX_CORNER:
            x, y = m("vertices", a), m("lines", b)
            key = None if x is None or y is None else (kind, x, y)
        elif kind in (TestKind.END_EVIDENCE, TestKind.SKU_SPLIT_SEAM, TestKind.SKU_SIZE,
                      TestKind.SKU_TILING, TestKind.SKU_SEEN_TILING,
                      TestKind.HEIGHT_WITHIN_BOX):
            # b: a side, a cut, a listed size: the same on both runs of one attempt
            x = m("attempts", a)
            key = None if x is None else (kind, x, b)
        elif kind in (TestKind.BOX_HEIGHT, TestKind.LAYER_HEIGHT,
                      TestKind.HEIGHT_SKU_AGREEMENT, TestKind.SEEN_CARTON):
            # b (the height's source; the layer mate whose height it took; a seen carton's
            # index in the scan's list) may change: one row per attempt
            x = m("attempts", a)
            key = None if x is None else (kind, x)
        elif kind in (TestKind.NEIGHBOUR_CORNER, TestKind.ROW_END):
            # b is a vertex id of its own version: rows follow the parent, in order
            x = m("hypotheses", a)
            key = None if x is None else (kind, x)
        else:
            key = None
        if key is None:
            continue
        k = seen.get(key, 0)  # several rows per entity (EDGE_SUPPORT peaks, BOUNDARY sides)
        seen[key] = k + 1
        out[(*key, k)] = r
    return out


def _test_row(t: TestTable, r: int) -> dict[str, Any]:
    return {"a": int(t.a[r]), "b": int(t.b[r]), "statistic": float(t.statistic[r]),
            "critical": float(t.critical[r]), "dof": float(t.dof[r]),
            "accepted": bool(t.accepted[r])}


def flipped_tests(
    stage: str, ta: TestTable, tb: TestTable, maps: Mapping[str, ItemMatch]
) -> list[FlippedTest]:
    """Tests of one stage, on matched entities, whose decision differs."""
    ka = _test_keys(ta, {})
    kb = _test_keys(tb, {k: v.cand_to_base() for k, v in maps.items()})
    out = []
    for key in sorted(set(ka) & set(kb)):
        ra, rb = ka[key], kb[key]
        if bool(ta.accepted[ra]) != bool(tb.accepted[rb]):
            out.append(FlippedTest(stage, TestKind(key[0]).name, _test_row(ta, ra),
                                   _test_row(tb, rb)))
    return out


def _test_counts(ta: TestTable | None, tb: TestTable | None) -> dict[str, dict[str, list[int]]]:
    """Per kind, [tested, accepted] of each run, where they differ."""
    def counts(t: TestTable | None) -> dict[int, list[int]]:
        if t is None:
            return {}
        out: dict[int, list[int]] = {}
        for k in np.unique(t.kind):
            sel = t.kind == k
            out[int(k)] = [int(sel.sum()), int(t.accepted[sel].sum())]
        return out

    ca, cb = counts(ta), counts(tb)
    res = {}
    for k in sorted(set(ca) | set(cb)):
        x, y = ca.get(k, [0, 0]), cb.get(k, [0, 0])
        if x != y:
            res[TestKind(k).name] = {"base": x, "candidate": y}
    return res


# --- surfaces --------------------------------------------------------------------------------


def compare_surfaces(a: SurfaceSet, b: SurfaceSet, tol: SurfaceTol,
                     up: np.ndarray | None = None) -> SurfaceDiff:
    """Pair surfaces by centre distance (optimal assignment) and measure what changed.

    Parameters
    ----------
    up : ndarray (3,), optional
        The scan's up direction in the sensor frame (``scan.up``). The pick order goes
        top-most first, so two surfaces of one layer swap places on any re-fit; with
        ``up``, a swap counts (``pick_order_significant``) only between surfaces whose
        heights differ by more than ``tol.pick_height_mm``.
    """
    na, nb = len(a), len(b)
    out = SurfaceDiff()
    pairs: list[tuple[int, int]] = []
    if na and nb:
        d = np.linalg.norm(a.centers[:, None] - b.centers[None], axis=-1)
        pairs = _assign(np.where(d * 1e3 <= tol.pair_gate_mm, d, np.inf))
    for i, j in sorted(pairs):
        dc = float(np.linalg.norm(a.centers[i] - b.centers[j])) * 1e3
        dn = float(_angle_deg(a.normals[i], b.normals[j]))
        # in-plane yaw: the x axes as lines (a rectangle is symmetric under a half turn)
        dy = float(_angle_deg(a.x_axis[i], b.x_axis[j], unsigned=True))
        dw = (float(b.width[j]) - float(a.width[i])) * 1e3
        dl = (float(b.length[j]) - float(a.length[i])) * 1e3
        moved = (dc > tol.center_mm or max(dn, dy) > tol.angle_deg
                 or differs(a.width[i] * 1e3, b.width[j] * 1e3, tol.dim_mm, tol.dim_rtol)
                 or differs(a.length[i] * 1e3, b.length[j] * 1e3, tol.dim_mm, tol.dim_rtol))
        ha, hb = float(a.height[i]) * 1e3, float(b.height[j]) * 1e3
        src = (_height_source(a, i), _height_source(b, j))
        sku = (int(a.sku[i]), int(b.sku[j]))
        flag = (bool(a.sku_flagged[i]), bool(b.sku_flagged[j]))
        out.pairs.append(SurfacePair(
            i, j, dc, dn, dy, dw, dl, int(a.pick_order[i]), int(b.pick_order[j]), moved,
            height_mm=(_finite(ha), _finite(hb)), height_source=src,
            height_changed=differs(ha, hb, tol.height_mm) or src[0] != src[1],
            sku=sku, sku_flagged=flag, sku_changed=sku[0] != sku[1] or flag[0] != flag[1]))
    paired_a = {p.base for p in out.pairs}
    paired_b = {p.candidate for p in out.pairs}
    out.removed = [i for i in range(na) if i not in paired_a]
    out.added = [j for j in range(nb) if j not in paired_b]
    # relative pick order of the surfaces both runs found, in baseline ids
    out.pick_order_base = [p.base for p in sorted(out.pairs, key=lambda p: p.pick_base)]
    out.pick_order_candidate = [p.base for p in sorted(out.pairs, key=lambda p: p.pick_candidate)]
    pos = {i: k for k, i in enumerate(out.pick_order_candidate)}
    seq = out.pick_order_base
    h = None if up is None else np.asarray(a.centers, np.float64) @ np.asarray(up, np.float64)
    for x in range(len(seq)):
        for y in range(x + 1, len(seq)):
            i, j = seq[x], seq[y]
            if pos[i] > pos[j]:
                dh = None if h is None else abs(float(h[i] - h[j])) * 1e3
                out.swaps.append((i, j, dh))
                if dh is None or dh > tol.pick_height_mm:
                    out.pick_order_significant = True
    return out


def _finite(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _height_source(s: SurfaceSet, i: int) -> str:
    try:
        return HeightSource(int(s.height_source[i])).name
    except ValueError:
        return str(int(s.height_source[i]))


def _reason_name(r: int) -> str:
    try:
        return AmbiguityReason(int(r)).name
    except ValueError:
        return str(int(r))


def compare_ambiguous(a: AmbiguousSet, b: AmbiguousSet, tol: SurfaceTol) -> AmbiguousDiff:
    """Pair ambiguous regions by the distance of their outlines' centres (optimal
    assignment, gated by ``tol.ambiguous_gate_mm``) and measure what changed: the centre
    beyond ``ambiguous_center_mm``, the extent beyond ``ambiguous_dim_mm``, or the reason."""
    na, nb = len(a), len(b)
    out = AmbiguousDiff(na, nb)
    ca = np.asarray(a.corners, np.float64).mean(axis=1) if na else np.zeros((0, 3))
    cb = np.asarray(b.corners, np.float64).mean(axis=1) if nb else np.zeros((0, 3))
    pairs: list[tuple[int, int]] = []
    if na and nb:
        d = np.linalg.norm(ca[:, None] - cb[None], axis=-1)
        ok = np.isfinite(d) & (d * 1e3 <= tol.ambiguous_gate_mm)
        pairs = _assign(np.where(ok, d, np.inf))
    for i, j in sorted(pairs):
        dc = float(np.linalg.norm(ca[i] - cb[j])) * 1e3
        wa, wb = float(a.width[i]) * 1e3, float(b.width[j]) * 1e3
        la, lb = float(a.length[i]) * 1e3, float(b.length[j]) * 1e3
        reason = (_reason_name(a.reason[i]), _reason_name(b.reason[j]))
        changed = (dc > tol.ambiguous_center_mm or reason[0] != reason[1]
                   or differs(wa, wb, tol.ambiguous_dim_mm)
                   or differs(la, lb, tol.ambiguous_dim_mm))
        out.pairs.append(AmbiguousPair(i, j, dc, wb - wa, lb - la, reason, changed))
    out.removed = [i for i in range(na) if i not in {p.base for p in out.pairs}]
    out.added = [j for j in range(nb) if j not in {p.candidate for p in out.pairs}]
    return out


# --- ground truth ----------------------------------------------------------------------------


def truth_for_scan(scan: Any, sources: Sequence[str] = _TRUTH_SOURCES) -> Any:
    """The ground truth of a recorded scan, or None (see ``[scores] truth``).

    ``simulator``: the scan's ``meta["simulator"]`` spec is simulated again and used only if
    it reproduces the recorded range bit for bit (NaN where NaN). ``npz``: the scan's
    ``source`` is an existing ``.npz`` with ``truth/`` arrays whose image size matches.
    """
    from boxloc.simulate import SceneSpec, load_truth, simulate

    for src in sources:
        if src == "simulator":
            spec = scan.meta.get("simulator") if isinstance(scan.meta, dict) else None
            if not isinstance(spec, dict):
                continue
            try:
                sim = simulate(SceneSpec.from_dict(spec))
            except (BoxlocError, TypeError, ValueError, KeyError):
                continue
            if sim.scan.range.shape == scan.range.shape and np.array_equal(
                    sim.scan.range, scan.range, equal_nan=True):
                return sim.truth
        elif src == "npz":
            p = Path(str(scan.source or ""))
            if p.suffix.lower() != ".npz" or not p.is_file():
                continue
            try:
                truth = load_truth(p)
            except BoxlocError:
                continue
            if truth is not None and tuple(truth.face_ids.shape) == tuple(scan.range.shape):
                return truth
    return None


def _score(surfaces: SurfaceSet, truth: Any, tol: ScoreTol) -> Any:
    from boxloc.evaluate.metrics import match_surfaces

    return match_surfaces(surfaces, truth, iou_min=tol.iou_min,
                          max_normal_deg=tol.max_normal_deg,
                          max_plane_offset=tol.max_plane_offset_mm / 1e3)


# --- one scan --------------------------------------------------------------------------------


def _counts(products: Mapping[str, Any]) -> dict[str, int | None]:
    def n(stage: str) -> int | None:
        p = products.get(stage)
        return None if p is None else len(p)

    h = products.get("hypotheses")
    v = products.get("verification")
    s = products.get("selection")
    ln = products.get("lines")
    return {
        "edges": n("edges"), "lines": n("lines"),
        "hough_trials": None if ln is None else int(ln.n_trials),
        "vertices": n("vertices"), "hypotheses": n("hypotheses"),
        "attempts": None if h is None else h.n_attempts,
        "verified": None if v is None else int(np.count_nonzero(v.accepted)),
        "candidates": n("selection"),
        "chosen": None if s is None else int(np.count_nonzero(s.chosen)),
        "surfaces": n("surfaces"),
        # None: the log predates the record (or the scan failed before its result)
        "ambiguous": n(AMBIGUOUS),
    }


def _same_input(a: Any, b: Any) -> str | None:
    """Why two scan records are not of the same input, or None."""
    if a.scan.range.shape != b.scan.range.shape:
        return f"range images differ in size ({a.scan.range.shape} vs {b.scan.range.shape})"
    if np.ascontiguousarray(a.scan.range).tobytes() != np.ascontiguousarray(
            b.scan.range).tobytes():
        return "range images differ (not the same input)"
    if a.scan.sensor.to_dict() != b.scan.sensor.to_dict():
        return "sensor models differ (not the same input)"
    return None


def _failure_text(err: Mapping[str, Any] | None) -> str | None:
    if not err:
        return None
    return f"{err.get('error_type', '')} in {err.get('stage') or 'pipeline'}: " \
           f"{err.get('message', '')}".rstrip(": ")


class _ScanComparison:
    """Builds the :class:`ScanDiff` of one pair of scan records."""

    def __init__(self, log: str, a: Any, b: Any, tol: Tolerances,
                 outcomes: Mapping[int, Any], truth: Any) -> None:
        self.a, self.b, self.tol = a, b, tol
        self.outcomes = outcomes
        self.truth = truth
        self.sd = ScanDiff(log=log, scan=int(a.index), status="changed")

    def add(self, stage: str, kind: str, message: str, rule: str | None = None,
            **values: Any) -> Difference:
        d = Difference(self.sd.scan, stage, kind, message, rule, values)
        d = dataclasses.replace(d, regression=is_regression(d, self.tol))
        self.sd.differences.append(d)
        return d

    def run(self) -> ScanDiff:
        a, b, sd = self.a, self.b, self.sd
        sd.timing = {"base": dict(a.timing_ms), "candidate": dict(b.timing_ms)}
        why = _same_input(a, b)
        if why is not None:
            sd.status, sd.error = "error", why
            return sd
        pa, pb = a.products, b.products
        cb = _counts(pb)
        sd.counts = {k: (v, cb[k]) for k, v in _counts(pa).items()}
        fa, fb = _failure_text(a.error), _failure_text(b.error)
        sd.failures = {"base": fa, "candidate": fb}
        changed = []
        ignore = tuple(self.tol.ignore.fields)
        for s in STAGES:
            if (s in pa) != (s in pb):
                if s not in OPTIONAL_STAGES:  # else one log predates the stage
                    changed.append(s)
            elif s in pa:
                changed += [f"{s}/{n}" for n in products_equal(pa[s], pb[s], ignore=ignore)]
        if (AMBIGUOUS in pa) != (AMBIGUOUS in pb):
            # one log predates the record: only regions the other one has are a change
            if len(pa[AMBIGUOUS] if AMBIGUOUS in pa else pb[AMBIGUOUS]):
                changed.append(AMBIGUOUS)
        elif AMBIGUOUS in pa:
            changed += [f"{AMBIGUOUS}/{n}" for n in products_equal(pa[AMBIGUOUS], pb[AMBIGUOUS],
                                                                  ignore=ignore)]
        sd.changed_fields = changed
        sd.identical = not changed and fa == fb
        if fb and not fa:
            self.add("scan", "scan_failed", f"the candidate failed: {fb}", "scan_failed")
        elif fa and not fb:
            self.add("scan", "scan_recovered", f"the baseline failed ({fa}); the candidate "
                     "ran", None)
        elif fa != fb:
            self.add("scan", "scan_failed", f"both failed, differently: {fa} / {fb}", None)
        scores_a = scores_b = None
        if self.truth is not None and "surfaces" in pa and "surfaces" in pb:
            scores_a = _score(pa["surfaces"], self.truth, self.tol.scores)
            scores_b = _score(pb["surfaces"], self.truth, self.tol.scores)
            sd.scores = {"base": scores_a.to_dict(), "candidate": scores_b.to_dict()}
        if sd.identical:
            sd.status = "identical"
            # the result is the same, but a pick outcome is still worth a line in the report
            if "surfaces" in pa:
                sd.surfaces = compare_surfaces(pa["surfaces"], pb["surfaces"],
                                               self.tol.surfaces, a.scan.up)
                self._picks()
            return sd
        self._stages()
        if "surfaces" in pa and "surfaces" in pb:
            sd.surfaces = compare_surfaces(pa["surfaces"], pb["surfaces"], self.tol.surfaces,
                                           a.scan.up)
            exempt = self._picks()
            self._surfaces(exempt, scores_a, scores_b)
            self._ambiguous(a.ambiguous, b.ambiguous)
        if not sd.differences:
            sd.status = "equivalent"
        return sd

    # -- intermediate stages --

    def _stages(self) -> None:
        a, b, sd, tol = self.a.products, self.b.products, self.sd, self.tol
        pixel_angle = float(self.a.scan.sensor.pixel_angle)
        for k, (x, y) in sd.counts.items():
            if x != y and k not in ("surfaces", AMBIGUOUS):  # results: judged by their rules
                self.add(k if k in STAGES else {"hough_trials": "lines", "attempts":
                         "hypotheses", "verified": "verification", "candidates": "selection",
                         "chosen": "selection"}[k], "count", f"{k}: {x} -> {y}",
                         "stage_counts", what=k, base=x, candidate=y)
        if "edges" in a and "edges" in b:
            la, lb = a["edges"].labels, b["edges"].labels
            if la.shape == lb.shape:
                sd.edge_pixels_changed = int(np.count_nonzero(la != lb))
                if sd.edge_pixels_changed:
                    self.add("edges", "edge_map",
                             f"{sd.edge_pixels_changed} edge-map pixel(s) changed label",
                             "stage_counts", pixels=sd.edge_pixels_changed)
        if "lines" in a and "lines" in b:
            sd.items["lines"] = match_lines(a["lines"], b["lines"], tol.match, pixel_angle)
        if "vertices" in a and "vertices" in b:
            sd.items["vertices"] = match_vertices(a["vertices"], b["vertices"], tol.match,
                                                  pixel_angle)
        if "hypotheses" in a and "hypotheses" in b and "vertices" in sd.items:
            sd.items["hypotheses"], sd.items["attempts"] = match_hypotheses(
                a["hypotheses"], b["hypotheses"], sd.items["vertices"], tol.match)
        for name, im in sd.items.items():
            stage = "hypotheses" if name == "attempts" else name
            if im.only_base:
                self.add(stage, "only_base", f"{len(im.only_base)} of {im.n_base} {name} "
                         "of the baseline have no match in the candidate", "stage_counts",
                         what=name, ids=im.only_base)
            if im.only_candidate:
                self.add(stage, "only_candidate", f"{len(im.only_candidate)} of "
                         f"{im.n_candidate} {name} of the candidate are new", "stage_counts",
                         what=name, ids=im.only_candidate)
            if im.changed:
                self.add(stage, "changed", f"{len(im.changed)} {name} kept another "
                         "rectangle", "stage_counts", what=name, items=im.changed)
        maps = dict(sd.items)
        if "hypotheses" in sd.items:
            maps["peaks"] = _same_peaks(a["hypotheses"], b["hypotheses"], sd.items["hypotheses"],
                                        tol.match)
        for stage in STAGES:
            if stage in a and stage in b and hasattr(a[stage], "tests"):
                tc = _test_counts(a[stage].tests, b[stage].tests)
                sd.test_counts.update(tc)
            if stage in TEST_STAGES and stage in a and stage in b:
                sd.flipped += flipped_tests(stage, a[stage].tests, b[stage].tests, maps)
        if AMBIGUOUS in a and AMBIGUOUS in b:
            sd.test_counts.update(_test_counts(a[AMBIGUOUS].tests, b[AMBIGUOUS].tests))
            sd.flipped += flipped_tests(AMBIGUOUS, a[AMBIGUOUS].tests, b[AMBIGUOUS].tests, maps)
        by_kind: dict[str, int] = {}
        for f in sd.flipped:
            by_kind[f.kind] = by_kind.get(f.kind, 0) + 1
        for kind, n in sorted(by_kind.items()):
            stage = next(f.stage for f in sd.flipped if f.kind == kind)
            self.add(stage, "flipped", f"{n} {kind} test(s) flipped decision", "flipped_tests",
                     test=kind, n=n)

    # -- annotated picks --

    def _picks(self) -> set[int]:
        """The fate of annotated picks; returns the surfaces exempt from the surface rules."""
        sd = self.sd
        exempt: set[int] = set()
        pair_of = {p.base: p for p in sd.surfaces.pairs}
        removed = set(sd.surfaces.removed)
        for sid, o in sorted(self.outcomes.items()):
            p = pair_of.get(sid)
            fate = "removed" if sid in removed else ("moved" if p is not None and p.moved
                                                     else "unchanged")
            if sid not in removed and p is None:
                fate = "unknown"  # the id is not a surface of the baseline
            rec = {"surface": sid, "ok": bool(o.ok), "reason": o.reason, "fate": fate,
                   "candidate": None if p is None else p.candidate}
            sd.picks.append(rec)
            why = f" ({o.reason})" if o.reason else ""
            if not o.ok:
                if fate in ("removed", "moved"):
                    exempt.add(sid)
                    verb = "dropped" if fate == "removed" else "changed"
                    self.add("picks", "failed_pick", f"surface #{sid}, whose pick failed{why}, "
                             f"is {verb} by the candidate", "failed_pick_changed", **rec)
                elif fate == "unchanged":
                    self.add("picks", "failed_pick", f"surface #{sid}, whose pick failed{why}, "
                             "is still chosen unchanged", "failed_pick_unchanged", **rec)
            elif fate in ("removed", "moved"):
                verb = "dropped" if fate == "removed" else "changed"
                self.add("picks", "ok_pick", f"surface #{sid}, picked successfully, is {verb} "
                         "by the candidate", "ok_pick_changed", **rec)
        return exempt

    # -- the result --

    def _surfaces(self, exempt: set[int], ma: Any, mb: Any) -> None:
        s = self.sd.surfaces
        judged_by_truth = ma is not None and self.tol.regression.truth_decides
        for i in s.removed:
            rule = None if (i in exempt or judged_by_truth) else "surface_removed"
            self.add("surfaces", "surface_removed", f"surface #{i} of the baseline is gone",
                     rule, base=i)
        for j in s.added:
            rule = None if judged_by_truth else "surface_added"
            self.add("surfaces", "surface_added", f"surface #{j} of the candidate is new",
                     rule, candidate=j)
        for p in s.moved:
            rule = None if (p.base in exempt or judged_by_truth) else "surface_moved"
            self.add("surfaces", "surface_moved",
                     f"surface #{p.base} -> #{p.candidate} moved: centre {p.dcenter_mm:.1f} mm, "
                     f"angle {p.dangle_deg:.2f} deg, width {p.dwidth_mm:+.1f} mm, length "
                     f"{p.dlength_mm:+.1f} mm", rule, **p.to_json())
        # a baseline log older than schema 1.5 could not record heights, sizes or ambiguous
        # regions (it has no /boxloc/ambiguous record): what the candidate adds there is
        # reported, not judged (as a stage a log predates is not a difference)
        old = AMBIGUOUS not in self.a.products
        note = " (the baseline's log predates box heights and sizes)" if old else ""

        def sku(k: int, flagged: bool) -> str:
            return f"size {k}" if k >= 0 else ("no listed size (flagged)" if flagged
                                               else "no size")

        for p in s.pairs:
            if p.height_changed:
                hb, hc = (("n/a" if h is None else f"{h:.0f} mm") for h in p.height_mm)
                new = old and p.height_mm[0] is None and p.height_source[0] == "NONE"
                self.add("surfaces", "height_changed",
                         f"surface #{p.base} -> #{p.candidate}: height {hb} "
                         f"({p.height_source[0].lower()}) -> {hc} "
                         f"({p.height_source[1].lower()})" + (note if new else ""),
                         None if new else "height_changed", **p.to_json())
            if p.sku_changed:
                new = old and p.sku[0] < 0 and not p.sku_flagged[0]
                self.add("surfaces", "sku_changed",
                         f"surface #{p.base} -> #{p.candidate}: {sku(p.sku[0], p.sku_flagged[0])}"
                         f" -> {sku(p.sku[1], p.sku_flagged[1])}" + (note if new else ""),
                         None if new else "sku_changed", **p.to_json())
        if s.pick_order_changed:
            note = "" if s.pick_order_significant else (
                f" (only between surfaces within {self.tol.surfaces.pick_height_mm:g} mm of "
                "the same height: not a change of layer)")
            self.add("surfaces", "pick_order",
                     f"pick order (baseline ids) {s.pick_order_base} -> "
                     f"{s.pick_order_candidate}{note}",
                     "pick_order" if s.pick_order_significant else None,
                     base=s.pick_order_base, candidate=s.pick_order_candidate,
                     swaps=s.swaps)
        if ma is None or mb is None:
            return
        if mb.tp < ma.tp:
            self.add("scores", "tp_lost", f"true positives {ma.tp} -> {mb.tp}", "tp_lost",
                     base=ma.tp, candidate=mb.tp)
        if mb.fp > ma.fp:
            self.add("scores", "fp_gained", f"false positives {ma.fp} -> {mb.fp}", "fp_gained",
                     base=ma.fp, candidate=mb.fp)
        if (ma.precision, ma.recall) != (mb.precision, mb.recall) and not (
                mb.tp < ma.tp or mb.fp > ma.fp):
            self.add("scores", "score", f"precision {ma.precision:.3f} -> {mb.precision:.3f}, "
                     f"recall {ma.recall:.3f} -> {mb.recall:.3f}", None,
                     precision=[ma.precision, mb.precision], recall=[ma.recall, mb.recall])
        # the same face found by both: did its centre get worse?
        face_a = {int(f): int(p) for p, f in ma.tp_pairs}
        err_a = {int(f): float(e) for (_, f), e in zip(ma.tp_pairs, ma.center_err)}
        err_b = {int(f): float(e) for (_, f), e in zip(mb.tp_pairs, mb.center_err)}
        for f in sorted(set(err_a) & set(err_b)):
            grow = (err_b[f] - err_a[f]) * 1e3
            if grow > self.tol.scores.center_err_mm:
                self.add("scores", "error_grew", f"face {f} (surface #{face_a[f]}): centre error "
                         f"{err_a[f] * 1e3:.1f} -> {err_b[f] * 1e3:.1f} mm", "error_grew",
                         face=f, base_mm=err_a[f] * 1e3, candidate_mm=err_b[f] * 1e3)

    def _ambiguous(self, a: AmbiguousSet, b: AmbiguousSet) -> None:
        """Ambiguous regions added, removed or changed (extent, place, reason)."""
        ad = self.sd.ambiguous = compare_ambiguous(a, b, self.tol.surfaces)
        if ad.added or ad.removed:
            self.add(AMBIGUOUS, "count", f"ambiguous regions: {ad.n_base} -> {ad.n_candidate}",
                     None, what=AMBIGUOUS, base=ad.n_base, candidate=ad.n_candidate)
        for i in ad.removed:
            self.add(AMBIGUOUS, "ambiguous_removed", f"ambiguous region #{i} of the baseline "
                     f"({_reason_name(a.reason[i]).lower()}) is gone", "ambiguous_removed",
                     base=i)
        old = AMBIGUOUS not in self.a.products  # a baseline that could not record any
        for j in ad.added:
            self.add(AMBIGUOUS, "ambiguous_added", f"ambiguous region #{j} of the candidate "
                     f"({_reason_name(b.reason[j]).lower()}) is new"
                     + (" (the baseline's log predates ambiguous regions)" if old else ""),
                     None if old else "ambiguous_added", candidate=j)
        for p in ad.changed:
            why = "" if p.reason[0] == p.reason[1] else (
                f", reason {p.reason[0].lower()} -> {p.reason[1].lower()}")
            self.add(AMBIGUOUS, "ambiguous_changed",
                     f"ambiguous region #{p.base} -> #{p.candidate} changed: centre "
                     f"{p.dcenter_mm:.1f} mm, width {p.dwidth_mm:+.1f} mm, length "
                     f"{p.dlength_mm:+.1f} mm{why}", "ambiguous_changed", **p.to_json())


def diff_scans(a: Any, b: Any, tolerances: Tolerances | None = None, *, log: str = "",
               outcomes: Mapping[int, Any] | None = None, truth: Any = None) -> ScanDiff:
    """Compare two :class:`recorder.mcap.log.ScanRecord` of the same scan.

    Parameters
    ----------
    outcomes : mapping, optional
        ``{surface id: PickOutcome}`` of the baseline's scan (latest per surface).
    truth : GroundTruth-like, optional
        The scan's ground truth (:func:`truth_for_scan`).
    """
    tol = tolerances or load_tolerances()
    return _ScanComparison(log, a, b, tol, outcomes or {}, truth).run()


# --- logs and directories --------------------------------------------------------------------


def _merge_join(base: Iterable[Any], cand: Iterable[Any]) -> Iterator[tuple[Any, Any]]:
    """Pairs (base, candidate) of records by scan index; None for a side without it.

    Streams in file order: a candidate in the same order as the baseline (the usual case)
    holds one record of each side in memory at a time.
    """
    it = iter(cand)
    pending: dict[int, Any] = {}
    done = False
    for a in base:
        c = pending.pop(a.index, None)
        while c is None and not done:
            nxt = next(it, None)
            if nxt is None:
                done = True
            elif nxt.index == a.index:
                c = nxt
            else:
                pending[nxt.index] = nxt
        yield a, c
    for c in [*pending.values(), *it]:
        yield None, c


def _config_changes(a: Any, b: Any) -> dict[str, list[Any]]:
    if a is None or b is None:
        return {}
    da, db = a.to_dict(), b.to_dict()

    def flat(d: Mapping[str, Any], p: str = "") -> dict[str, Any]:
        out: dict[str, Any] = {}
        for k, v in d.items():
            if isinstance(v, Mapping):
                out.update(flat(v, f"{p}{k}."))
            else:
                out[f"{p}{k}"] = v
        return out

    fa, fb = flat(da), flat(db)
    return {k: [fa.get(k), fb.get(k)] for k in sorted(set(fa) | set(fb))
            if fa.get(k) != fb.get(k)}


def _pooled(log_diff: LogDiff, matches: list[tuple[Any, Any]]) -> None:
    from boxloc.evaluate.metrics import aggregate_matches

    if not matches:
        return
    pa = aggregate_matches([m for m, _ in matches])
    pb = aggregate_matches([m for _, m in matches])
    log_diff.pooled = {"base": _jsonable(pa), "candidate": _jsonable(pb)}
    tol = log_diff.tolerances
    for key, rule, unit in (("precision", "precision_drop", ""), ("recall", "recall_drop", ""),
                            ("center_err_median_mm", "center_err_mm", " mm"),
                            ("dim_err_median_mm", "dim_err_mm", " mm")):
        x, y = pa.get(key), pb.get(key)
        if x == y:
            continue
        fx = "n/a" if x is None else f"{x:.3f}{unit}"
        fy = "n/a" if y is None else f"{y:.3f}{unit}"
        d = Difference(None, "scores", "score", f"pooled {key}: {fx} -> {fy}", rule,
                       {"what": key, "base": x, "candidate": y})
        log_diff.differences.append(dataclasses.replace(d, regression=is_regression(d, tol)))


def diff_logs(base: str | os.PathLike[str], candidate: str | os.PathLike[str],
              tolerances: Tolerances | None = None) -> LogDiff:
    """Compare two boxloc logs scan by scan (matched by sequence = scan index).

    A log that cannot be read does not raise: the :class:`LogDiff` carries the error (exit
    code 2), so a directory of logs is still compared as a whole.

    Raises
    ------
    InputError
        A path that does not exist.
    """
    from recorder.mcap.log import open_log

    tol = tolerances or load_tolerances()
    pa, pb = Path(base), Path(candidate)
    for p in (pa, pb):
        if not p.exists():
            raise InputError(f"log not found: {p}")
        if p.is_dir():
            raise InputError(f"{p} is a directory; diff_logs takes two .mcap files "
                             "(diff_paths compares directories)")
    ld = LogDiff(base=pa, candidate=pb, tolerances=tol)
    matches: list[tuple[Any, Any]] = []
    try:
        la, lb = open_log(pa), open_log(pb)
        ld.config_changes = _config_changes(la.config, lb.config)
        ld.versions = {"base": la.version, "candidate": lb.version,
                       "base_commit": la.run.get("git_commit", ""),
                       "candidate_commit": lb.run.get("git_commit", "")}
        by_scan: dict[int, dict[int, Any]] = {}
        for (si, sid), o in la.latest_outcomes().items():
            by_scan.setdefault(int(si), {})[int(sid)] = o
        for a, b in _merge_join(la.scans(), lb.scans()):
            if b is None:
                sd = ScanDiff(log=pa.name, scan=int(a.index), status="missing")
                d = Difference(sd.scan, "scan", "scan_missing",
                               f"scan {a.index} is missing from the candidate", "scan_missing")
                sd.differences.append(dataclasses.replace(d, regression=is_regression(d, tol)))
                ld.scans.append(sd)
                continue
            if a is None:
                sd = ScanDiff(log=pa.name, scan=int(b.index), status="extra")
                sd.differences.append(Difference(sd.scan, "scan", "scan_extra",
                                                 f"scan {b.index} is only in the candidate"))
                ld.scans.append(sd)
                continue
            truth = truth_for_scan(a.scan, tol.scores.truth) if tol.scores.truth else None
            sd = diff_scans(a, b, tol, log=pa.name, outcomes=by_scan.get(int(a.index)),
                            truth=truth)
            if truth is not None and "surfaces" in a.products and "surfaces" in b.products:
                matches.append((_score(a.products["surfaces"], truth, tol.scores),
                                _score(b.products["surfaces"], truth, tol.scores)))
            ld.scans.append(sd)
    except (BoxlocError, OSError) as e:
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        ld.error = msg if isinstance(e, LogError | BoxlocError) else f"{type(e).__name__}: {msg}"
        return ld
    _pooled(ld, matches)
    return ld


def list_logs(directory: Path) -> dict[str, Path]:
    """The ``.mcap`` files of a directory (not recursive), by file name."""
    return {p.name: p for p in sorted(directory.iterdir())
            if p.is_file() and p.suffix.lower() == ".mcap"}


def diff_paths(base: str | os.PathLike[str], candidate: str | os.PathLike[str],
               tolerances: Tolerances | None = None) -> list[LogDiff]:
    """Compare two logs, or two directories of logs matched by file name.

    A log only in the baseline directory is an error of its own (its :class:`LogDiff` has
    ``error`` set: exit code 2); a log only in the candidate directory is reported the same
    way, since a replay must produce one log per recorded log.

    Raises
    ------
    InputError
        A missing path, a file compared with a directory, or directories without logs.
    """
    tol = tolerances or load_tolerances()
    pa, pb = Path(base), Path(candidate)
    for p in (pa, pb):
        if not p.exists():
            raise InputError(f"not found: {p}")
    if pa.is_dir() != pb.is_dir():
        raise InputError(f"cannot compare a {'directory' if pa.is_dir() else 'file'} ({pa}) "
                         f"with a {'directory' if pb.is_dir() else 'file'} ({pb})")
    if not pa.is_dir():
        return [diff_logs(pa, pb, tol)]
    la, lb = list_logs(pa), list_logs(pb)
    if not la and not lb:
        raise InputError(f"no .mcap logs in {pa} or {pb}")
    out = []
    for name in sorted(set(la) | set(lb)):
        if name not in lb:
            out.append(LogDiff(pa / name, pb / name, tol,
                               error=f"{name} is missing from the candidate directory"))
        elif name not in la:
            out.append(LogDiff(pa / name, pb / name, tol,
                               error=f"{name} is only in the candidate directory"))
        else:
            out.append(diff_logs(la[name], lb[name], tol))
    return out


__all__ = [
    "AmbiguousDiff", "AmbiguousPair", "compare_ambiguous",
    "Difference", "FlippedTest", "ItemMatch", "LogDiff", "ScanDiff", "SurfaceDiff",
    "SurfacePair", "Tolerances", "compare_surfaces", "diff_logs", "diff_paths", "diff_scans",
    "differs", "flipped_tests", "is_regression", "list_logs", "load_tolerances",
    "match_hypotheses", "match_lines", "match_vertices", "regression", "truth_for_scan",
]

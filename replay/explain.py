"""Post-mortem: the chain of decisions behind a surface, or why an expected one is missing.

Everything is read back from a log: every product of the scan and every statistical test
(:class:`boxloc.stats.TestTable`), so nothing is recomputed and the explanation is exactly
what the recorded run decided.

For a chosen surface (``surface=K``), the chain of the paper's Fig. 2 backwards:

* the MDL selection (line 9): its q_ii, the candidates it overlapped, those it beat;
* the hypothesis and its *generating vertex* (line 3), the vertex's two lines (support,
  Hough trial, votes) and the vertex tests LINES_MEET / LINES_ORTHOGONAL / AT_SEGMENT_ENDS,
  each as statistic against critical value;
* where the dimensions came from (lines 4-8): a diagonal vertex with its COPLANAR /
  PARALLEL / FIRST_QUADRANT tests, or the edge accumulators A_x, A_y with their peaks and
  the EDGE_SUPPORT tests |P_f| > p;
* every attempt of that hypothesis and its verification (lines 16, 29): the VERIFY_* tests
  and the reason of the first failure.

For a place where a surface was expected (``at=(x, y)`` in pixels, or ``(x, y, z)`` in the
sensor frame, metres), the chain forward, to where it stopped: the region of the range
image around the point that no edge crosses, the edge points that bound it, the lines those
edge points support, the vertices of those lines (or the vertex tests their pairs failed),
the hypotheses whose rectangles contain the point, their verification, and the MDL
selection they lost (and to what).

:func:`explain` returns plain data (``--json``); :func:`format_explanation` makes it
readable in a terminal.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from boxloc.config import Config
from boxloc.errors import InputError
from boxloc.jsonable import jsonable as _jsonable
from boxloc.products import (
    NOISE_FIELDS,
    AmbiguityReason,
    AmbiguousSet,
    DimensionSource,
    EdgeKind,
    HeightSource,
    NoiseSource,
    SelectReason,
    VerifyReason,
)
from boxloc.scan import NoiseModel
from boxloc.stages.hypotheses import SIZE_PART
from boxloc.stages.vertices import THIRD_EDGE
from boxloc.stats import (
    BUDGET_EDGES,
    BUDGET_HYPOTHESES,
    BUDGET_HYPOTHESIS_WORK,
    BUDGET_LINES,
    FURTHER_CONDITIONS,
    RELATION,
    TestKind,
    TestTable,
    numbers_accept,
)

_NEGATE = {"<=": ">", "<": ">=", ">": "<=", ">=": "<"}
#: what each verify reason's failing test is: the first rejected row of these kinds
_REASON_TEST: dict[VerifyReason, tuple[TestKind, ...]] = {
    VerifyReason.TILTED: (TestKind.VERIFY_TILT,),
    VerifyReason.INTERIOR_EDGES: (TestKind.VERIFY_INTERIOR,),
    VerifyReason.BOUNDARY: (TestKind.VERIFY_BOUNDARY,),
    VerifyReason.INTERIOR_SEAM: (TestKind.VERIFY_SEAM_INTERIOR, TestKind.VERIFY_SEAM_MIDLINE),
    VerifyReason.NOT_EXPOSED: (TestKind.VERIFY_EXPOSED,),
    VerifyReason.INLIERS: (TestKind.VERIFY_INLIERS,),
    VerifyReason.MEAN_OFFSET: (TestKind.VERIFY_MEAN,),
    VerifyReason.CONTINUES: (TestKind.VERIFY_CONTINUATION, TestKind.VERIFY_RAISED_BEYOND),
    VerifyReason.OUTSIDE_IMAGE: (TestKind.VERIFY_CONTINUATION,),
}
#: SEAM_PEAK's b: the axis, and where the search looked (:mod:`boxloc.stages.hypotheses`)
_SEAM_AXES = ("along x", "along y", "along x, near max_edge", "along y, near max_edge")
#: the four sides of a rectangle, in the order of the VERIFY_BOUNDARY rows
_SIDES = ("side at the vertex along x", "far side along x", "side at the vertex along y",
          "far side along y")
#: lists in an explanation are cut to this many items (the JSON says how many there were)
MAX_ITEMS = 12
#: the sides of END_EVIDENCE rows (b = 0-3), as boxloc.stats.TestKind.END_EVIDENCE names them
_END_SIDES = ("side v = 0", "side v = length", "side u = 0", "side u = width")
#: END_EVIDENCE statistic levels
_EVIDENCE = {0: "no evidence", 1: "a line of jump or convex-crease edges",
             2: "a groove or seam", 3: "a listed size's implied seam",
             4: "the verified outline of the region it lies in",
             5: "the face's plane dropping away beyond it"}
#: what each ambiguity reason means, for people
_AMBIGUITY_TEXT = {
    AmbiguityReason.NO_END_EVIDENCE: "a side has no evidence of a box's end (no jump, "
                                     "crease, groove, seam or listed size)",
    AmbiguityReason.LARGER_THAN_MAX_BOX: "it is longer than the longest box edge (max_edge): "
                                         "several boxes whose seams the range points do not "
                                         "show",
    AmbiguityReason.NOT_A_MULTIPLE_OF_A_SIZE: "it is no multiple (1x1, 2x1, 3x1, 2x2, ...) of "
                                              "a listed carton size",
    AmbiguityReason.SEVERAL_SPLITS: "it is a multiple of more than one listed size (or of "
                                    "one in two ways) and no seam shows which",
    AmbiguityReason.TOO_LOW_FOR_THE_SIZE: "it stands less than the listed carton's height "
                                          "above what lies beyond its sides (a bare pallet)",
    AmbiguityReason.SEVERAL_TILINGS: "it is a grid of a listed size, but the cartons can be "
                                     "laid over its outline another way too (turned: a "
                                     "brick, pinwheel or basket weave), and its seams do "
                                     "not show which way",
    AmbiguityReason.MULTIPLE_OF_A_NEIGHBOUR: "it is two or more of a box found beside it in "
                                             "its plane (REPEATS_NEIGHBOUR): as many "
                                             "cartons whose seams the range points do not "
                                             "show, or one box",
}
#: the tests behind an ambiguous region or a box's size and height
_REGION_TESTS = (TestKind.END_EVIDENCE, TestKind.SKU_SPLIT_SEAM, TestKind.SKU_SIZE,
                 TestKind.SKU_TILING, TestKind.SKU_SEEN_TILING)
_HEIGHT_TEXT = {HeightSource.SIDE: "from its visible side face",
                HeightSource.STEP: "from the step down to its neighbour or the layer below",
                HeightSource.SKU: "the matched carton size's height",
                HeightSource.NONE: "not measured"}


def _name(enum: type, v: int) -> str:
    try:
        return enum(int(v)).name
    except ValueError:
        return str(int(v))


def _mm(v: Any) -> float | None:
    f = float(v)
    return round(f * 1e3, 2) if math.isfinite(f) else None


def _vec(v: Any, digits: int = 4) -> list[float | None]:
    return [round(float(x), digits) if math.isfinite(float(x)) else None for x in v]


def _tests(t: TestTable, kinds: Sequence[TestKind], *, a: int | None = None,
           b: int | None = None, pair: tuple[int, int] | None = None) -> list[dict[str, Any]]:
    """Rows of ``t`` of the given kinds on the given entities, as plain dicts."""
    m = np.isin(t.kind, [int(k) for k in kinds])
    if a is not None:
        m &= t.a == a
    if b is not None:
        m &= t.b == b
    if pair is not None:
        x, y = pair
        m &= ((t.a == x) & (t.b == y)) | ((t.a == y) & (t.b == x))
    return t.select(m).rows()


@dataclass
class _Ctx:
    """One recorded scan and what it takes to explain it."""

    log_path: str
    rec: Any
    config: Config

    def __post_init__(self) -> None:
        products = self.rec.products
        self.edges = products.get("edges")
        self.lines = products.get("lines")
        self.vertices = products.get("vertices")
        self.hypotheses = products.get("hypotheses")
        self.verification = products.get("verification")
        self.selection = products.get("selection")
        self.surfaces = products.get("surfaces")
        amb = products.get("ambiguous")
        self.ambiguous: AmbiguousSet = amb if amb is not None else AmbiguousSet()
        self.scan = self.rec.scan

    # -- entities --

    def line(self, i: int) -> dict[str, Any]:
        L = self.lines
        return {
            "id": i, "kind": _name(EdgeKind, L.kinds[i]), "n_support": int(L.n_support[i]),
            "trial": int(L.trial[i]), "direction_votes": float(L.direction_votes[i]),
            "position_votes": float(L.position_votes[i]),
            "length_mm": _mm(np.linalg.norm(L.ends[i] - L.starts[i])),
            "start": _vec(L.starts[i]), "end": _vec(L.ends[i]),
            "tests": _tests(L.tests, [TestKind.POINT_ON_LINE], a=i),
        }

    def vertex(self, v: int) -> dict[str, Any]:
        V = self.vertices
        la, lb = int(V.line_a[v]), int(V.line_b[v])
        par, side = int(V.parent[v]), int(V.parent_side[v])
        lines_tests = [TestKind.LINES_MEET, TestKind.LINES_ORTHOGONAL, TestKind.AT_SEGMENT_ENDS]
        if side == THIRD_EDGE:  # the parent's two lines, and the corner's own test
            tests = (_tests(V.tests, lines_tests,
                            pair=(int(V.line_a[par]), int(V.line_b[par])))
                     + _tests(V.tests, [TestKind.BOX_CORNER], a=par, b=max(la, lb)))
        elif par >= 0 and side == SIZE_PART:  # a part of the parent's split region: its
            tests = []  # SKU_SPLIT_SEAM rows are the part's verification's
        elif par >= 0:  # offered from the parent's seam side
            tests = _tests(V.tests, [TestKind.NEIGHBOUR_CORNER], a=par)
        else:
            tests = _tests(V.tests, lines_tests, pair=(la, lb))
        return {
            "id": v, "point": _vec(V.points[v]), "normal": _vec(V.normals[v]),
            "d1": _vec(V.d1[v]), "d2": _vec(V.d2[v]), "line_a": la, "line_b": lb,
            # a neighbour's corner: the vertex whose verified rectangle's seam side it ends;
            # a box corner's (side THIRD_EDGE): the vertex of two lines it comes from
            "parent": par, "parent_side": side,
            "lines": ([self.line(i) for i in (la, lb) if i >= 0]
                      if self.lines is not None else []),
            "tests": tests,
        }

    def attempts_of(self, h: int) -> list[int]:
        return [int(j) for j in np.flatnonzero(self.hypotheses.att_hypothesis == h)]

    def attempt(self, j: int) -> dict[str, Any]:
        H = self.hypotheses
        src = DimensionSource(int(H.att_source[j]))
        d: dict[str, Any] = {
            "id": j, "hypothesis": int(H.att_hypothesis[j]), "source": src.name,
            "diagonal": int(H.att_diagonal[j]), "width_mm": _mm(H.att_width[j]),
            "length_mm": _mm(H.att_length[j]),
            # the diagonal's test statistic total (vertices) or |P_f| (edges), and its bound
            "support": float(H.att_support[j]), "threshold": float(H.att_threshold[j]),
            "verified": bool(H.att_verified[j]),
        }
        V = self.verification
        if V is not None and j < len(V):
            reason = VerifyReason(int(V.reason[j]))
            tests = _tests(V.tests, [k for k in TestKind if k >= TestKind.VERIFY_INLIERS
                                     and k not in (TestKind.SEAM_PEAK, TestKind.FACE_EXTENT,
                                                   TestKind.NEIGHBOUR_CORNER)],
                           a=j)
            sides = iter(_SIDES)
            for t in tests:  # one row per side, in the order boxloc.stages.verify tests them
                if t["kind"] == TestKind.VERIFY_BOUNDARY.name:
                    t["side"] = next(sides, "")
            failed = None
            if reason in _REASON_TEST:
                kinds = {k.name for k in _REASON_TEST[reason]}
                failed = next((t for t in tests if t["kind"] in kinds and not t["accepted"]),
                              None)
            d["verification"] = {
                "accepted": bool(V.accepted[j]), "reason": reason.name,
                "failed_test": failed,
                "n_inside": int(V.n_inside[j]), "n_valid": int(V.n_valid[j]),
                "n_inliers": int(V.n_inliers[j]), "n_front": int(V.n_front[j]),
                "n_behind": int(V.n_behind[j]),
                "inlier_fraction": float(V.inlier_fraction[j]),
                "mean_distance_mm": _mm(V.mean_distance[j]),
                "sigma_mean_mm": _mm(V.sigma_mean[j]),
                "n_interior_edges": int(V.n_interior_edges[j]), "rms_mm": _mm(V.rms[j]),
                "tests": tests,
            }
        if self.selection is not None:
            k = np.flatnonzero(self.selection.candidates == j)
            if k.size:
                d["selection"] = self.candidate(int(k[0]), brief=True)
        return d

    def surface_of_attempt(self, j: int) -> int | None:
        if self.surfaces is None:
            return None
        k = np.flatnonzero(self.surfaces.attempt == j)
        return int(k[0]) if k.size else None

    def candidate(self, k: int, *, brief: bool = False) -> dict[str, Any]:
        """Candidate k of the MDL selection: its terms, its fate, its competitors."""
        S = self.selection
        j = int(S.candidates[k])
        order = [int(x) for x in S.order]
        d: dict[str, Any] = {
            "candidate": k, "attempt": j, "hypothesis": int(S.hypothesis[k]),
            "chosen": bool(S.chosen[k]), "reason": _name(SelectReason, S.reason[k]),
            "q_ii": float(S.Q[k, k]), "n_points": int(S.n_points[k]),
            "error": float(S.error[k]), "n_params": int(S.n_params[k]),
            "order": order.index(k) if k in order else None, "n_chosen": len(order),
        }
        b = int(S.beaten_by[k])
        if b >= 0:
            d["beaten_by"] = {"candidate": b, "attempt": int(S.candidates[b]),
                              "hypothesis": int(S.hypothesis[b]), "q_ii": float(S.Q[b, b]),
                              "q_ij": float(S.Q[k, b]),
                              "surface": self.surface_of_attempt(int(S.candidates[b]))}
        if brief:
            return d
        d.update(k1=S.k1, k2=S.k2, k3=S.k3, objective=float(S.objective),
                 face_points=float(S.face_points),
                 unit=float(S.unit[k]) if np.isfinite(S.unit[k]) else None)
        comp: list[dict[str, Any]] = []
        for c in range(len(S)):
            if c == k or S.Q[k, c] == 0.0:
                continue  # q_ij is 0 exactly when the two share no inlier
            comp.append({
                "candidate": c, "attempt": int(S.candidates[c]),
                "hypothesis": int(S.hypothesis[c]), "q_jj": float(S.Q[c, c]),
                "q_ij": float(S.Q[k, c]), "chosen": bool(S.chosen[c]),
                "reason": _name(SelectReason, S.reason[c]),
                "beaten_by_this": int(S.beaten_by[c]) == k,
                "surface": self.surface_of_attempt(int(S.candidates[c])),
            })
        comp.sort(key=lambda x: x["q_ij"])  # most negative: the largest overlap
        d["n_overlapping"] = len(comp)
        d["overlapping"] = comp[:MAX_ITEMS]
        d["beat"] = [x["candidate"] for x in comp if x["beaten_by_this"]]
        return d

    def dimensions(self, h: int, j: int | None) -> dict[str, Any]:
        """Where hypothesis h's dimensions (of attempt j, if any) came from."""
        H = self.hypotheses
        t = H.tests
        diag_tests = _tests(t, [TestKind.COPLANAR, TestKind.PARALLEL,
                                TestKind.FIRST_QUADRANT], a=h)
        by_vertex: dict[int, list[dict[str, Any]]] = {}
        for r in diag_tests:
            by_vertex.setdefault(int(r["b"]), []).append(r)
        diag = [{"vertex": v, "passed": all(r["accepted"] for r in rows), "tests": rows}
                for v, rows in sorted(by_vertex.items())]
        lo, hi = int(H.peaks_x_offsets[h]), int(H.peaks_x_offsets[h + 1])
        px = H.peaks_x[lo:hi]
        lo, hi = int(H.peaks_y_offsets[h]), int(H.peaks_y_offsets[h + 1])
        py = H.peaks_y[lo:hi]
        ax = H.acc_x[int(H.acc_x_offsets[h]):int(H.acc_x_offsets[h + 1])]
        ay = H.acc_y[int(H.acc_y_offsets[h]):int(H.acc_y_offsets[h + 1])]
        bin_m = float(H.acc_bin[h])

        def votes(acc: np.ndarray, m: float) -> int:
            if not acc.size or not math.isfinite(bin_m) or bin_m <= 0:
                return 0
            i = int(m / bin_m)
            return int(acc[max(i - 1, 0):i + 2].sum())

        support = _tests(t, [TestKind.EDGE_SUPPORT], a=h)
        if j is not None and DimensionSource(int(H.att_source[j])) == DimensionSource.EDGES:
            for r in support:  # the row that made this attempt
                r["used"] = bool(np.isclose(r["statistic"], H.att_support[j])
                                 and np.isclose(r["critical"], H.att_threshold[j]))
        edges = {
            "n_candidates": int(H.n_candidates[h]),
            "point_on_plane": _tests(t, [TestKind.POINT_ON_PLANE], a=h),
            "bin_mm": _mm(bin_m),
            "peaks_x": [{"at_mm": _mm(m), "votes": votes(ax, m)} for m in px],
            "peaks_y": [{"at_mm": _mm(m), "votes": votes(ay, m)} for m in py],
            "edge_support": support,
            # seams (lines of range points behind the plane) that gave extra candidates
            "seams": _tests(t, [TestKind.SEAM_PEAK], a=h),
            # how far the face's plane runs along each arm (candidates of their own)
            "extent": _tests(t, [TestKind.FACE_EXTENT], a=h),
        }
        d: dict[str, Any] = {
            "source": "NONE" if j is None else DimensionSource(int(H.att_source[j])).name,
            "diagonal_candidates": diag[:MAX_ITEMS], "n_diagonal_candidates": len(diag),
            "edges": edges,
        }
        if j is not None and int(H.att_diagonal[j]) >= 0 and self.vertices is not None:
            v = int(H.att_diagonal[j])
            d["diagonal"] = {"vertex": v, "point": _vec(self.vertices.points[v]),
                             "tests": by_vertex.get(v, [])}
        return d

    def hypothesis(self, h: int, focus: int | None = None) -> dict[str, Any]:
        H = self.hypotheses
        kept = int(H.attempt[h])
        j = focus if focus is not None else (kept if kept >= 0 else None)
        atts = self.attempts_of(h)
        v = int(H.vertex[h])
        return {
            "id": h, "vertex": self.vertex(v) if self.vertices is not None else {"id": v},
            "kept_attempt": kept if kept >= 0 else None,
            "dimensions": self.dimensions(h, j),
            "n_attempts": len(atts),
            "attempts": [self.attempt(a) for a in atts],
        }

    def surface(self, k: int) -> dict[str, Any]:
        S = self.surfaces
        if S is None:
            raise InputError(f"scan {self.scan.index} has no surfaces (its pipeline stopped: "
                             f"{(self.rec.error or {}).get('message', 'incomplete')})")
        if not 0 <= k < len(S):
            raise InputError(f"scan {self.scan.index} has {len(S)} surface(s); no surface {k}"
                             + (" (ids are 0-based)" if len(S) else ""))
        h, j = int(S.hypothesis[k]), int(S.attempt[k])
        kk = np.flatnonzero(self.selection.candidates == j)
        return {
            "surface": k, "pick_order": int(S.pick_order[k]), "center": _vec(S.centers[k]),
            "normal": _vec(S.normals[k]), "width_mm": _mm(S.width[k]),
            "length_mm": _mm(S.length[k]), "score": float(S.scores[k]),
            # the lid's middle above the rim's plane, and whether the centre sits on the rim
            "bulge_mm": _mm(S.bulge[k]),
            "tests": _tests(S.tests, [TestKind.SURFACE_BULGE], a=j),
            "height": self.height(k), "size": self.size(k),
            "hypothesis": self.hypothesis(h, focus=j), "attempt": j,
            "selection": self.candidate(int(kk[0])) if kk.size else None,
        }


    def height(self, k: int) -> dict[str, Any]:
        """Surface k's box height: value, sigma, source and its BOX_HEIGHT test, after its
        HEIGHT_WITHIN_BOX rows (measurements deeper than any carton is tall, not used), its
        LAYER_HEIGHT test where its flush layer's smallest measurement was weighed, and its
        HEIGHT_SKU_AGREEMENT test where a listed height was weighed."""
        S = self.surfaces
        return {"height_mm": _mm(S.height[k]), "sigma_mm": _mm(S.height_sigma[k]),
                "source": _name(HeightSource, S.height_source[k]),
                "tests": _tests(S.tests, [TestKind.HEIGHT_WITHIN_BOX, TestKind.LAYER_HEIGHT,
                                          TestKind.HEIGHT_SKU_AGREEMENT, TestKind.BOX_HEIGHT],
                                a=int(S.attempt[k]))}

    def size(self, k: int) -> dict[str, Any]:
        """Surface k against the carton list: the matched size (row of
        ``Config.box_sizes``) or the flag, and the SKU_SIZE tests."""
        S = self.surfaces
        sku = int(S.sku[k])
        listed = self.config.box_sizes
        return {"n_listed": len(listed), "sku": sku if sku >= 0 else None,
                "listed_mm": ([_mm(v) for v in listed[sku]] if 0 <= sku < len(listed)
                              else None),
                "flagged": bool(S.sku_flagged[k]),
                "tests": _tests(S.tests, [TestKind.SKU_SIZE], a=int(S.attempt[k]))}

    def ambiguous_region(self, k: int) -> dict[str, Any]:
        """Ambiguous region k: why it is not a surface, its extent and the tests behind it
        (its own rows, then the hypothesis and verification rows of its attempt)."""
        A = self.ambiguous
        j = int(A.attempt[k])
        rows: list[dict[str, Any]] = A.tests_of(k).rows() if j >= 0 else []
        seen = {(r["kind"], r["a"], r["b"], r["statistic"]) for r in rows}
        for prod in (self.hypotheses, self.verification):
            if prod is None or j < 0:
                continue
            for r in _tests(prod.tests, _REGION_TESTS, a=j):
                if (r["kind"], r["a"], r["b"], r["statistic"]) not in seen:
                    rows.append(r)
        # the region's own evidence first (END_EVIDENCE, SKU_*), then its attempt's others
        region_kinds = {k.name for k in _REGION_TESTS}
        rows.sort(key=lambda r: r["kind"] not in region_kinds)
        for r in rows:
            r["region_test"] = r["kind"] in region_kinds
            if r["kind"] == TestKind.END_EVIDENCE.name and 0 <= int(r["b"]) < 4:
                r["side"] = _END_SIDES[int(r["b"])]
                r["evidence"] = _EVIDENCE.get(int(r["statistic"]), str(r["statistic"]))
        try:
            reason = AmbiguityReason(int(A.reason[k]))
            reason_name, text = reason.name, _AMBIGUITY_TEXT[reason]
        except (ValueError, KeyError):
            reason_name = text = str(int(A.reason[k]))
        if reason_name == AmbiguityReason.LARGER_THAN_MAX_BOX.name:
            text += (f" ({_num(_mm(A.length[k]))} mm against max_edge "
                     f"{_num(_mm(self.config.max_edge))} mm)")
        return {"region": k, "reason": reason_name, "reason_text": text,
                "hypothesis": int(A.hypothesis[k]), "attempt": j,
                "width_mm": _mm(A.width[k]), "length_mm": _mm(A.length[k]),
                "area_m2": float(A.area[k]), "corners": [_vec(c) for c in A.corners[k]],
                "n_listed_sizes": len(self.config.box_sizes), "tests": rows}

    def ambiguous_at(self, P: np.ndarray) -> int | None:
        """The ambiguous region whose outline contains P (in its plane, within half the
        shortest box edge, as for rectangles), or None."""
        A = self.ambiguous
        tol_w = 0.5 * self.config.min_edge
        for k in range(len(A)):
            c = np.asarray(A.corners[k], np.float64)
            ex, ey = c[1] - c[0], c[3] - c[0]
            W_, L_ = float(np.linalg.norm(ex)), float(np.linalg.norm(ey))
            if not (W_ > 0 and L_ > 0 and math.isfinite(W_ + L_)):
                continue
            n = np.cross(ex, ey)
            n /= np.linalg.norm(n) or 1.0
            D = P - c[0]
            u, v, w = float(D @ ex) / W_, float(D @ ey) / L_, float(D @ n)
            if 0 <= u <= W_ and 0 <= v <= L_ and abs(w) <= tol_w:
                return k
        return None


# --- a point where a surface was expected ----------------------------------------------------


def _parse_at(at: Any) -> tuple[float, ...]:
    if isinstance(at, str):
        try:
            vals = tuple(float(v) for v in at.replace(" ", "").split(","))
        except ValueError:
            raise InputError(f"--at must be X,Y (pixels) or X,Y,Z (metres), got {at!r}") from None
    else:
        try:
            vals = tuple(float(v) for v in at)
        except (TypeError, ValueError):
            raise InputError(f"at must be (x, y) pixels or (x, y, z) metres, got {at!r}") from None
    if len(vals) not in (2, 3) or not all(math.isfinite(v) for v in vals):
        raise InputError(f"--at must be X,Y (pixels) or X,Y,Z (metres), got {at!r}")
    return vals


def _locate(ctx: _Ctx, at: tuple[float, ...]) -> dict[str, Any]:
    """The pixel (row, col) and the 3D point of ``at``."""
    scan = ctx.scan
    H, W = scan.shape
    P = scan.points
    if len(at) == 2:
        x, y = at
        col, row = int(round(x)), int(round(y))
        if not (0 <= row < H and 0 <= col < W):
            raise InputError(f"pixel ({x:g}, {y:g}) is outside the {W}x{H} image")
        out: dict[str, Any] = {"given": "pixel", "pixel": [col, row]}
    else:
        X = np.asarray(at, np.float64)
        uv = scan.sensor.project(X[None])[0]
        if not np.isfinite(uv).all() or not (-0.5 <= uv[0] < W - 0.5 and -0.5 <= uv[1] < H - 0.5):
            raise InputError(f"point {tuple(at)} (sensor frame, metres) is not seen by the "
                             "sensor")
        col, row = int(round(uv[0])), int(round(uv[1]))
        out = {"given": "point", "pixel": [col, row], "point": _vec(X)}
    if np.isfinite(P[row, col]).all():
        out["point"] = out.get("point") or _vec(P[row, col])
        out["range_m"] = float(scan.range[row, col])
        return out
    # no return here: the nearest pixel with one, a few pixels away at most
    r0, r1 = max(row - 3, 0), min(row + 4, H)
    c0, c1 = max(col - 3, 0), min(col + 4, W)
    rr, cc = np.nonzero(scan.valid[r0:r1, c0:c1])
    out["no_return"] = True
    if rr.size:
        k = int(np.argmin((rr + r0 - row) ** 2 + (cc + c0 - col) ** 2))
        out["used_pixel"] = [int(cc[k] + c0), int(rr[k] + r0)]
        out["point"] = out.get("point") or _vec(P[rr[k] + r0, cc[k] + c0])
    return out


def _region(ctx: _Ctx, row: int, col: int, P0: np.ndarray) -> tuple[np.ndarray, int]:
    """The face around (row, col): pixels connected to it that no edge crosses and that lie
    on its plane, within the largest box diagonal. Mask (H, W) and its size.

    The edge map alone does not close a face (its boundary has gaps wherever the edge
    detector found nothing), so the region is also held to the plane fitted to the 5x5
    pixels around the point: a neighbouring box top at another height, or the floor, is
    not part of it.
    """
    scan, cfg = ctx.scan, ctx.config
    H, W = scan.shape
    P = scan.points.astype(np.float64)
    r0, r1, c0, c1 = max(row - 2, 0), min(row + 3, H), max(col - 2, 0), min(col + 3, W)
    win = P[r0:r1, c0:c1].reshape(-1, 3)
    win = win[np.isfinite(win).all(axis=1)]
    if win.shape[0] < 3:
        return np.zeros((H, W), bool), 0
    c = win.mean(axis=0)
    n = np.linalg.eigh((win - c).T @ (win - c))[1][:, 0]
    rng = float(np.linalg.norm(P0))
    # on the plane: a few sigma of range noise, plus the flatness prior and one pixel's
    # footprint of the plane's tilt (a coarse sensor's neighbours differ by that much)
    tol = 4.0 * float(np.sqrt(cfg.noise.sigma_range(rng) ** 2 + cfg.flatness ** 2)) + \
        rng * float(scan.sensor.pixel_angle)
    with np.errstate(invalid="ignore"):
        on_plane = np.abs((P - c) @ n) <= tol
        near = np.linalg.norm(P - P0, axis=-1) <= math.sqrt(2.0) * cfg.max_edge
    free = scan.valid & on_plane & near & (ctx.edges.labels == 0)
    if not free[row, col]:  # on an edge or a hole: start from a free neighbour
        for dr, dc in sorted(((a, b) for a in (-2, -1, 0, 1, 2) for b in (-2, -1, 0, 1, 2)),
                             key=lambda t: t[0] ** 2 + t[1] ** 2):
            r, cc = row + dr, col + dc
            if 0 <= r < H and 0 <= cc < W and free[r, cc]:
                row, col = r, cc
                break
        else:
            return np.zeros((H, W), bool), 0
    comp, _ = ndimage.label(free)
    mask = comp == comp[row, col]
    return mask, int(mask.sum())


def _extent_mm(ctx: _Ctx, mask: np.ndarray) -> list[float | None]:
    """Length and width of a region along its principal axes, mm (a region much larger
    than one box means the face's own boundary was not found where it meets others)."""
    Q = ctx.scan.points[mask].astype(np.float64)
    Q = Q[np.isfinite(Q).all(axis=1)]
    if Q.shape[0] < 3:
        return [None, None]
    c = Q.mean(axis=0)
    axes = np.linalg.eigh((Q - c).T @ (Q - c))[1][:, ::-1][:, :2]
    t = (Q - c) @ axes
    ext = t.max(axis=0) - t.min(axis=0)
    return [_mm(ext[0]), _mm(ext[1])]


def _contains(ctx: _Ctx, P: np.ndarray) -> list[dict[str, Any]]:
    """Attempts whose rectangle contains P (in its plane, within half the shortest box edge)."""
    H = ctx.hypotheses
    out = []
    tol_w = 0.5 * ctx.config.min_edge  # a box top is never closer than this to another's
    for j in range(H.n_attempts):
        h = int(H.att_hypothesis[j])
        D = P - H.origins[h]
        u, v, w = float(D @ H.x_axis[h]), float(D @ H.y_axis[h]), float(D @ H.normals[h])
        W_, L_ = float(H.att_width[j]), float(H.att_length[j])
        if 0 <= u <= W_ and 0 <= v <= L_ and abs(w) <= tol_w:
            out.append({"attempt": j, "hypothesis": h, "u_mm": _mm(u), "v_mm": _mm(v),
                        "off_plane_mm": _mm(w)})
    return out


def explain_at(ctx: _Ctx, at: Any) -> dict[str, Any]:
    """Follow the chain at a point where a surface was expected, up to where it stopped."""
    where = _locate(ctx, _parse_at(at))
    out: dict[str, Any] = {"where": where}
    if where.get("no_return") and "used_pixel" not in where:
        out.update(stopped_at="scan", why="the sensor has no return at this pixel (nor within "
                   "3 pixels): there is nothing to localize here")
        return out
    if ctx.edges is None:
        out.update(stopped_at="edges", why="the pipeline stopped before the edge stage")
        return out
    P = np.asarray(where["point"], np.float64)
    col, row = where.get("used_pixel", where["pixel"])
    cfg = ctx.config
    mask, n_region = _region(ctx, row, col, P)
    # the edge points bounding that region (one pixel around it), near enough to matter
    ring = ndimage.binary_dilation(mask, iterations=2) & ~mask
    E = ctx.edges
    on_ring = ring[E.pixels[:, 0], E.pixels[:, 1]] if len(E) else np.zeros(0, bool)
    near = np.linalg.norm(E.points - P, axis=1) <= math.sqrt(2) * cfg.max_edge if len(E) \
        else np.zeros(0, bool)
    bound = np.flatnonzero(on_ring & near)
    kinds = {EdgeKind(int(k)).name: int(n) for k, n in
             zip(*np.unique(E.kinds[bound], return_counts=True))} if bound.size else {}
    out["region"] = {"n_pixels": n_region, "n_boundary_edges": int(bound.size),
                     "boundary_edge_kinds": kinds, "extent_mm": _extent_mm(ctx, mask)}
    # everything whose rectangle contains the point, whatever generated it
    contain = _contains(ctx, P) if ctx.hypotheses is not None else []
    out["containing_attempts"] = contain[:MAX_ITEMS]
    out["n_containing_attempts"] = len(contain)
    # a flat region reported as ambiguous is not a surface, whatever else contains it
    k_amb = ctx.ambiguous_at(P)
    if k_amb is not None:
        r = ctx.ambiguous_region(k_amb)
        missing = [t["side"] for t in r["tests"] if t["kind"] == TestKind.END_EVIDENCE.name
                   and not t["accepted"] and "side" in t]
        why = (f"ambiguous region #{k_amb} ({_num(r['width_mm'])} x {_num(r['length_mm'])} mm, "
               f"{r['area_m2']:.3f} m2) contains this point: a flat region whose extent the "
               f"evidence cannot split into boxes, so it is not a surface: {r['reason_text']}")
        if missing:
            why += f"; without evidence of an end: {', '.join(missing)}"
        if not r["n_listed_sizes"]:
            why += (" (no carton sizes were given: with --box-sizes, a region that is a "
                    "multiple of a listed size is split at the implied seams)")
        out.update(stopped_at="ambiguous", ambiguous=r, why=why)
        return out
    chosen = [c for c in contain if ctx.surface_of_attempt(c["attempt"]) is not None]
    if chosen:
        k = ctx.surface_of_attempt(chosen[0]["attempt"])
        assert k is not None
        out.update(stopped_at="chosen", surface=k,
                   why=f"surface #{k} (pick {int(ctx.surfaces.pick_order[k])}) contains this point",
                   explanation=ctx.surface(k))
        return out
    verified = [c for c in contain if bool(ctx.hypotheses.att_verified[c["attempt"]])]
    if verified:
        j = verified[0]["attempt"]
        a = ctx.attempt(j)
        s = a.get("selection", {})
        why = (f"hypothesis {a['hypothesis']} (attempt {j}, {a['width_mm']} x "
               f"{a['length_mm']} mm) was verified but lost the MDL selection: {s.get('reason')}"
               f" (q_ii = {s.get('q_ii', float('nan')):.1f})")
        if "beaten_by" in s:
            b = s["beaten_by"]
            sf = f", surface #{b['surface']}" if b.get("surface") is not None else ""
            why += (f", to attempt {b['attempt']} (hypothesis {b['hypothesis']}{sf}, "
                    f"q_jj = {b['q_ii']:.1f}, q_ij = {b['q_ij']:.1f})")
        out.update(stopped_at="selection", why=why,
                   attempts=[ctx.attempt(c["attempt"]) for c in verified[:MAX_ITEMS]])
        return out
    if contain:
        parts = []
        for c in contain[:4]:
            a = ctx.attempt(c["attempt"])
            v = a.get("verification", {})
            ft = v.get("failed_test")
            parts.append(f"attempt {a['id']} of hypothesis {a['hypothesis']} "
                         f"({a['source']}, {a['width_mm']} x {a['length_mm']} mm): "
                         f"{v.get('reason')}" + (f" ({_test_text(ft)})" if ft else ""))
        out.update(stopped_at="verification",
                   why="the rectangles that contain this point failed verification: "
                       + "; ".join(parts),
                   attempts=[ctx.attempt(c["attempt"]) for c in contain[:MAX_ITEMS]])
        return out
    # nothing contains the point: walk forward from the edges
    if not bound.size:
        out.update(stopped_at="edges", why=(
            f"no edge point bounds the region around this point ({n_region} pixels without "
            "an edge): its boundary was not detected, so no line, vertex or rectangle can "
            "come from it"))
        return out
    L = ctx.lines
    bset = set(int(i) for i in bound)
    line_ids = []
    if L is not None:
        for i in range(len(L)):
            shared = len(bset.intersection(int(s) for s in L.support_of(i)))
            if shared:
                line_ids.append((i, shared))
    line_ids.sort(key=lambda t: -t[1])
    out["lines"] = [{**ctx.line(i), "boundary_support": n} for i, n in line_ids[:MAX_ITEMS]]
    if not line_ids:
        n_trials = int(L.n_trials) if L is not None else 0
        out.update(stopped_at="lines", why=(
            f"{bound.size} edge point(s) bound the region ({_kinds_text(kinds)}), but no line "
            f"was fitted to them in {n_trials} Hough trial(s): too few collinear points, or "
            "a line shorter than half of min_edge"))
        return out
    lid = [i for i, _ in line_ids]
    V = ctx.vertices
    vids = [] if V is None else [int(v) for v in range(len(V))
                                 if int(V.line_a[v]) in lid or int(V.line_b[v]) in lid]
    if not vids:
        pair_tests: list[dict[str, Any]] = []
        if V is not None:
            for x in range(len(lid)):
                for y in range(x + 1, len(lid)):
                    rows = _tests(V.tests, [TestKind.LINES_MEET, TestKind.LINES_ORTHOGONAL,
                                            TestKind.AT_SEGMENT_ENDS], pair=(lid[x], lid[y]))
                    failed = [r for r in rows if not r["accepted"]]
                    pair_tests.append({"lines": [lid[x], lid[y]], "tests": rows,
                                       "failed": [r["kind"] for r in failed]})
        # the pair that came closest first: fewest failed tests, then the smallest excess
        def closeness(p: dict[str, Any]) -> tuple[int, float]:
            ratios = [r["statistic"] / r["critical"] for r in p["tests"]
                      if not r["accepted"] and r["critical"]]
            return len(p["failed"]), min(ratios, default=math.inf)

        pair_tests.sort(key=closeness)
        out["line_pairs"] = pair_tests[:MAX_ITEMS]
        first = next((p for p in pair_tests if p["failed"]), None)
        why = (f"the bounding lines {', '.join(f'L{i}' for i in lid[:6])} form no vertex")
        if len(lid) == 1:
            why += ": only one line bounds this region, a vertex needs two"
        elif first is not None:
            r = next(t for t in first["tests"] if not t["accepted"])
            why += (f": the closest pair, L{first['lines'][0]} and L{first['lines'][1]}, "
                    f"failed {_test_text(r)}")
        out.update(stopped_at="vertices", why=why)
        return out
    out["vertices"] = [ctx.vertex(v) for v in vids[:MAX_ITEMS]]
    hyps = [int(h) for h in np.flatnonzero(np.isin(ctx.hypotheses.vertex, vids))] \
        if ctx.hypotheses is not None else []
    out["hypotheses"] = [ctx.hypothesis(h) for h in hyps[:MAX_ITEMS]]
    parts = []
    for hd in out["hypotheses"][:4]:
        dims = hd["dimensions"]
        tilt = _tests(ctx.hypotheses.tests, [TestKind.HYPOTHESIS_TILT], a=hd["id"])
        if hd["n_attempts"] == 0 and tilt:
            parts.append(f"hypothesis {hd['id']} (vertex V{hd['vertex']['id']}): no rectangle "
                         f"was sought, its plane is tilted beyond max_tilt from up (a side "
                         f"face): {_test_text(tilt[0])}")
        elif hd["n_attempts"] == 0:
            n_diag = dims["n_diagonal_candidates"]
            sup = dims["edges"]["edge_support"]
            best = max(sup, key=lambda r: r["statistic"] - r["critical"], default=None)
            txt = (f"hypothesis {hd['id']} (vertex V{hd['vertex']['id']}): no dimensions: "
                   f"{n_diag} diagonal vertex candidate(s) "
                   f"({sum(1 for c in dims['diagonal_candidates'] if c['passed'])} passed), "
                   f"|P_c| = {dims['edges']['n_candidates']} coplanar edge points")
            if best is not None:
                txt += f", best {_test_text(best)}"
            parts.append(txt)
        else:
            rects = ", ".join(f"{a['width_mm']} x {a['length_mm']} mm" for a in
                              hd["attempts"][:3])
            parts.append(f"hypothesis {hd['id']} (vertex V{hd['vertex']['id']}): its "
                         f"rectangles ({rects}) do not contain this point")
    out.update(stopped_at="dimensions", why="vertices of the bounding lines gave no rectangle "
               "over this point: " + "; ".join(parts))
    return out


def _kinds_text(kinds: dict[str, int]) -> str:
    return ", ".join(f"{n} {k.lower()}" for k, n in kinds.items()) or "none"


# --- the entry point -------------------------------------------------------------------------


def _noise(noise: Any) -> dict[str, Any] | None:
    """The noise model the scan's tests used, where it came from and how it fits (None for
    a log written before the noise stage)."""
    if noise is None:
        return None
    model = dict(zip(NOISE_FIELDS, (float(v) for v in noise.model)))
    fit = noise.tests.of_kind(TestKind.NOISE_FIT)
    r = float(np.median(noise.bin_range)) if noise.bin_range.size else None
    worst = None
    if noise.bin_z.size:
        i = int(np.argmax(noise.bin_z))
        worst = {"range_m": float(noise.bin_range[i]), "tiles": int(noise.bin_tiles[i]),
                 "ratio": float(noise.bin_std[i] / noise.bin_model_std[i]),
                 "z": float(noise.bin_z[i]), "design_effect": float(noise.bin_design[i]),
                 "dof": float(noise.bin_dof[i])}
    return {
        "source": _name(NoiseSource, noise.source), "reason": noise.reason, "model": model,
        "range_m": r,
        "sigma_mm": None if r is None else 1e3 * float(NoiseModel(**model).sigma_range(r)),
        "fit": _tests(fit, [TestKind.NOISE_FIT])[0] if len(fit) else None,
        "worst_bin": worst,
        "tile_correlation": [float(v) for v in noise.tile_correlation],
    }


#: What each stage's BUDGET row counts.
_BUDGET_WORK = {BUDGET_EDGES: ("edges", "samples visited by the scan lines' split-and-merge"),
                BUDGET_LINES: ("lines", "neighbour points examined by the Hough trials"),
                BUDGET_HYPOTHESES: ("hypotheses", "vertices needing a rectangle search"),
                BUDGET_HYPOTHESIS_WORK: ("hypotheses", "pixels read by the rectangle searches")}


def _budgets(products: dict[str, Any]) -> list[dict[str, Any]]:
    """The stages that stopped at their work budget on this scan."""
    out = []
    for stage in ("edges", "lines", "hypotheses"):
        p = products.get(stage)
        if p is None:
            continue
        for row in p.tests.of_kind(TestKind.BUDGET).rows():
            name, what = _BUDGET_WORK.get(int(row["a"]), (stage, "work"))
            out.append({"stage": name, "work": row["statistic"], "budget": row["critical"],
                        "counts": what})
    return out


def explain(log: Any, scan: int, surface: int | None = None, at: Any = None,
            failed_picks: bool = False) -> dict[str, Any]:
    """The chain of decisions for a surface of a recorded scan (see the module notes).

    Parameters
    ----------
    log : path or recorder.mcap.log.Log
        A boxloc log (a truncated one is read up to its last good record).
    scan : int
        The scan index.
    surface : int, optional
        A surface id (its row in the scan's surfaces; 0 = first picked).
    at : str or sequence, optional
        ``"X,Y"`` / ``(x, y)`` pixels (column, row), or ``"X,Y,Z"`` / ``(x, y, z)`` metres
        in the sensor frame: a place where a surface was expected.
    failed_picks : bool
        Explain every surface of the scan whose (latest) pick outcome is a failure.

    With none of ``surface``, ``at``, ``failed_picks``: every surface of the scan.

    Returns
    -------
    dict
        JSON-ready (NaN as None).

    Raises
    ------
    InputError
        More than one of surface / at / failed_picks, no such surface, a bad ``at``.
    LogError
        The log cannot be read or has no such scan.
    """
    from recorder.mcap.log import Log, open_log

    modes = sum(x for x in (surface is not None, at is not None, bool(failed_picks)))
    if modes > 1:
        raise InputError("give only one of --surface, --at, --failed-picks")
    lg = log if isinstance(log, Log) else open_log(os.fspath(log), allow_truncated=True)
    rec = lg.scan(int(scan))
    ctx = _Ctx(str(lg.path), rec, lg.config or Config())
    S = ctx.surfaces
    out: dict[str, Any] = {
        "log": str(lg.path), "scan": int(scan), "alpha": ctx.config.alpha,
        "n_surfaces": None if S is None else len(S),
        "n_ambiguous": len(ctx.ambiguous),
        "pipeline_error": rec.error,
        "noise": _noise(rec.products.get("noise")),
        "budgets": _budgets(rec.products),
    }
    if failed_picks:
        out["mode"] = "failed_picks"
        outcomes = [o for (si, _), o in sorted(lg.latest_outcomes().items())
                    if si == int(scan) and not o.ok]
        out["surfaces"] = []
        for o in outcomes:
            e = ctx.surface(int(o.surface_id))
            e["pick"] = {"ok": False, "reason": o.reason, "source": o.source}
            out["surfaces"].append(e)
    elif at is not None:
        out["mode"] = "at"
        out["at"] = explain_at(ctx, at)
    else:
        out["mode"] = "surface"
        ids = [int(surface)] if surface is not None else list(range(len(S) if S else 0))
        out["surfaces"] = [ctx.surface(k) for k in ids]
    return _jsonable(out)


# --- text ------------------------------------------------------------------------------------


def _num(v: Any) -> str:
    if v is None:
        return "n/a"
    f = float(v)
    if not math.isfinite(f):
        return "n/a"
    if f == int(f) and abs(f) < 1e9:
        return str(int(f))
    return f"{f:.4g}"


def _test_text(t: dict[str, Any] | None) -> str:
    """``KIND a,b: s <= c (dof, p): accepted``: the relation the numbers show
    (:data:`boxloc.stats.RELATION`), and where the decision went the other way, the
    kind's further conditions that decided it."""
    if not t:
        return ""
    kind = TestKind[t["kind"]]
    sense = RELATION.get(kind, "<=")
    s, c = t.get("statistic"), t.get("critical")
    by_numbers = numbers_accept(kind, math.nan if s is None else s,
                                math.nan if c is None else c)
    holds = bool(t["accepted"]) if by_numbers is None else by_numbers
    if sense is None:
        rel = f"{_num(s)} (critical {_num(c)})"
    else:
        shown = sense if holds else _NEGATE[sense]
        rel = f"{_num(s)} {shown} {_num(c)}"
    extra = []
    if t.get("dof"):
        extra.append(f"chi2 {_num(t['dof'])} dof")
    p = t.get("p_value")
    if p is not None and math.isfinite(float(p)):
        extra.append(f"p = {_num(p)}")
    tail = f" ({', '.join(extra)})" if extra else ""
    verdict = "accepted" if t["accepted"] else "REJECTED"
    if holds != bool(t["accepted"]):
        why = FURTHER_CONDITIONS.get(kind, ("", ""))[0 if t["accepted"] else 1]
        verdict += f": {why}" if why else " (by the kind's further conditions, TestKind)"
    side = f" [{t['side']}]" if t.get("side") else ""
    if t.get("evidence"):
        side += f" ({t['evidence']})"
    return f"{t['kind']} {t['a']},{t['b']}{side}: {rel}{tail}: {verdict}"


def _point_text(v: list[Any] | None) -> str:
    """A recorded point as ``(+x, +y, +z) m``; "n/a" when it was not recorded."""
    if not v:
        return "n/a"
    return "(" + ", ".join("n/a" if x is None else f"{x:+.3f}" for x in v) + ") m"


def _line_text(ln: dict[str, Any]) -> str:
    return (f"L{ln['id']}: {ln['length_mm']} mm, {ln['kind'].lower()}, support "
            f"{ln['n_support']} edge points, Hough trial {ln['trial']}, votes "
            f"{_num(ln['direction_votes'])} (direction) / {_num(ln['position_votes'])} "
            "(position)")


def _vertex_lines(v: dict[str, Any], ind: str) -> list[str]:
    out = [f"{ind}generating vertex V{v['id']} at {_point_text(v.get('point'))}, normal "
           f"{_point_text(v.get('normal'))[:-2]}"]
    par, side = v.get("parent", -1), v.get("parent_side", -1)
    if par >= 0 and side == THIRD_EDGE:
        out.append(f"{ind}  a box corner: vertex V{par}'s crease and its third edge")
    elif par >= 0 and side == SIZE_PART:
        out.append(f"{ind}  a part's corner: vertex V{par}'s flat region, split at the seams "
                   f"a listed carton size implies")
    elif par >= 0:
        out.append(f"{ind}  a neighbour's corner, on side {side} of vertex V{par}'s rectangle")
    for ln in v.get("lines", []):
        out.append(f"{ind}  line {_line_text(ln)}")
        out += [f"{ind}    {_test_text(t)}" for t in ln["tests"]]
    if v.get("tests"):
        out.append(f"{ind}  vertex tests:")
        out += [f"{ind}    {_test_text(t)}" for t in v["tests"]]
    return out


def _dims_lines(d: dict[str, Any], ind: str) -> list[str]:
    out = [f"{ind}dimensions from {d['source']}"]
    if "diagonal" in d:
        g = d["diagonal"]
        out.append(f"{ind}  diagonal vertex V{g['vertex']} at {_point_text(g['point'])}")
        out += [f"{ind}    {_test_text(t)}" for t in g["tests"]]
    e = d["edges"]
    if d["source"] == "SEAMS":
        for t in e["seams"][:MAX_ITEMS]:
            b = int(t["b"])
            axis = _SEAM_AXES[b] if 0 <= b < len(_SEAM_AXES) else f"b = {b}"
            out.append(f"{ind}  seam {axis}: {_test_text(t)}")
    if d["source"] == "EDGES" or d["source"] == "NONE":
        if d["source"] == "NONE":
            out.append(f"{ind}  {d['n_diagonal_candidates']} diagonal vertex candidate(s)")
            for c in d["diagonal_candidates"][:4]:
                failed = [t for t in c["tests"] if not t["accepted"]]
                out.append(f"{ind}    V{c['vertex']}: " + ("passed" if c["passed"] else
                                                           "; ".join(_test_text(t) for t in
                                                                     failed)))
        out.append(f"{ind}  |P_c| = {e['n_candidates']} edge points coplanar and in the first "
                   f"quadrant; accumulator bin {e['bin_mm']} mm")
        px = ", ".join(f"{p['at_mm']} mm ({p['votes']} votes)" for p in e["peaks_x"]) or "none"
        py = ", ".join(f"{p['at_mm']} mm ({p['votes']} votes)" for p in e["peaks_y"]) or "none"
        out.append(f"{ind}  A_x peaks (width): {px}")
        out.append(f"{ind}  A_y peaks (length): {py}")
        for t in e["edge_support"][:MAX_ITEMS]:
            mark = "  <- used" if t.get("used") else ""
            out.append(f"{ind}    |P_f| vs p: {_test_text(t)}{mark}")
    return out


def _exposed_note(v: dict[str, Any]) -> str:
    """Where VERIFY_EXPOSED weighed its counts by the noise's correlation: how (its rows'
    counts are effective ones, the raw points beyond k over the design effect D)."""
    rows = [t for t in v.get("tests", ()) if t["kind"] == TestKind.VERIFY_EXPOSED.name]
    raw = int(v.get("n_front", 0)) + int(v.get("n_behind", 0))
    if not rows or not raw or int(rows[0]["b"]) in (raw, 0):
        return ""
    return (f"VERIFY_EXPOSED counts are effective: the noise's correlation weighs the {raw} "
            f"points beyond k as {int(rows[0]['b'])} independent ones "
            f"(design effect {raw / int(rows[0]['b']):.1f})")


def _attempt_lines(a: dict[str, Any], ind: str, *, focus: int | None = None) -> list[str]:
    v = a.get("verification", {})
    mark = "  <- this surface" if focus == a["id"] else ""
    head = (f"{ind}attempt {a['id']}: {a['source'].lower()}"
            + (f" (diagonal V{a['diagonal']})" if a["diagonal"] >= 0 else "")
            + f", {a['width_mm']} x {a['length_mm']} mm -> {v.get('reason', 'not verified')}"
            + mark)
    out = [head]
    if v and v["n_inside"]:
        out.append(f"{ind}  {v['n_inside']} pixels inside, {v['n_valid']} with a return, "
                   f"{v['n_inliers']} on the plane ({v['inlier_fraction']:.2f}), "
                   f"{v['n_front']} in front, {v['n_behind']} behind; mean distance "
                   f"{_num(v['mean_distance_mm'])} mm, rms {_num(v['rms_mm'])} mm, "
                   f"{v['n_interior_edges']} interior edge points")
        note = _exposed_note(v)
        if note:
            out.append(f"{ind}  {note}")
    if v:
        out += [f"{ind}  {_test_text(t)}" for t in v["tests"]]
        if v.get("failed_test"):
            out.append(f"{ind}  failed: {_test_text(v['failed_test'])}")
    s = a.get("selection")
    if s:
        out.append(f"{ind}  MDL: {s['reason'].lower()}, q_ii = {s['q_ii']:.1f}")
    return out


def _selection_lines(s: dict[str, Any] | None, ind: str) -> list[str]:
    if not s:
        return [f"{ind}not in the MDL selection"]
    order = s["order"]
    pos = f", added {order + 1} of {s['n_chosen']}" if order is not None else ""
    unit = s.get("unit")
    if s.get("face_points", 0.0) > 0 and unit is not None:
        # the model cost counted in smallest faces (Config.mdl_face_points), not pixels
        scaled = (f"K1 n - K2 xi - K3 N u / F with u / F = {unit:.0f} / "
                  f"{_num(s['face_points'])} (a smallest face's points here), ")
    else:
        scaled = "K1 n - K2 xi - K3 N with "
    out = [f"{ind}MDL selection: {s['reason'].lower()}, q_ii = {s['q_ii']:.1f} = "
           f"{scaled}n = {s['n_points']} points, xi = {s['error']:.1f}, "
           f"N = {s['n_params']} (K = {_num(s['k1'])}, {_num(s['k2'])}, {_num(s['k3'])})"
           f"{pos}; objective {s['objective']:.1f}"]
    if s["n_overlapping"]:
        out.append(f"{ind}  overlapping candidates ({s['n_overlapping']}):")
        for c in s["overlapping"]:
            what = "beaten by this one" if c["beaten_by_this"] else c["reason"].lower()
            sf = f", surface #{c['surface']}" if c["surface"] is not None else ""
            out.append(f"{ind}    attempt {c['attempt']} (hypothesis {c['hypothesis']}{sf}): "
                       f"q_jj = {c['q_jj']:.1f}, q_ij = {c['q_ij']:.1f}: {what}")
    else:
        out.append(f"{ind}  it overlapped no other candidate")
    return out


def _surface_lines(e: dict[str, Any], ind: str = "") -> list[str]:
    out = [f"{ind}surface #{e['surface']} (pick {e['pick_order']}): centre "
           f"{_point_text(e['center'])}, {e['width_mm']} x {e['length_mm']} mm, normal "
           f"{_point_text(e['normal'])[:-2]}, score {e['score']:.3f}"]
    for t in e.get("tests", []):  # SURFACE_BULGE: is the centre on the lid or on its rim?
        where = "on the rim's plane" if not t["accepted"] else "on the points' plane"
        out.append(f"{ind}  lid bulge {e['bulge_mm']} mm, centre {where}: {_test_text(t)}")
    out += _height_lines(e.get("height"), ind + "  ")
    out += _size_lines(e.get("size"), ind + "  ")
    if "pick" in e:
        out.append(f"{ind}  pick FAILED" + (f": {e['pick']['reason']}" if e["pick"]["reason"]
                                            else ""))
    out += _selection_lines(e.get("selection"), ind + "  ")
    h = e["hypothesis"]
    out.append(f"{ind}  hypothesis {h['id']}")
    out += _vertex_lines(h["vertex"], ind + "    ")
    out += _dims_lines(h["dimensions"], ind + "    ")
    out.append(f"{ind}    attempts of hypothesis {h['id']} ({h['n_attempts']}), in the order "
               "tried:")
    for a in h["attempts"]:
        out += _attempt_lines(a, ind + "      ", focus=e["attempt"])
    return out


def _height_lines(h: dict[str, Any] | None, ind: str) -> list[str]:
    if not h:
        return []
    try:
        how = _HEIGHT_TEXT[HeightSource[h["source"]]]
    except KeyError:
        how = f"source {h['source']}"
    took = [t for t in h["tests"] if t["kind"] == "LAYER_HEIGHT" and t["accepted"]]
    if took:  # not its own measurement: its flush layer's smallest
        how += f", measured on the top of attempt {took[0]['b']} of its flush layer"
    if h["height_mm"] is None:
        out = [f"{ind}box height {how}"]
    else:
        sig = f" +- {_num(h['sigma_mm'])} mm" if h["sigma_mm"] is not None else ""
        out = [f"{ind}box height {_num(h['height_mm'])} mm{sig}, {how}"]
    return out + [f"{ind}  {_test_text(t)}" for t in h["tests"]]


def _size_lines(z: dict[str, Any] | None, ind: str) -> list[str]:
    if not z or not (z["n_listed"] or z["tests"] or z["flagged"]):
        return []  # no carton list: nothing to say
    if z["sku"] is not None:
        dims = " x ".join(_num(v) for v in z["listed_mm"] or []) or "?"
        head = f"{ind}carton size: listed size {z['sku']} ({dims} mm)"
    elif z["flagged"]:
        head = f"{ind}carton size: FLAGGED, it matches none of the {z['n_listed']} listed sizes"
    else:
        head = f"{ind}carton size: not tested"
    return [head] + [f"{ind}  {_test_text(t)}" for t in z["tests"][:MAX_ITEMS]]


def _ambiguous_lines(r: dict[str, Any], ind: str) -> list[str]:
    out = [f"{ind}ambiguous region #{r['region']}: {r['reason'].lower()}, "
           f"{_num(r['width_mm'])} x {_num(r['length_mm'])} mm, {r['area_m2']:.3f} m2 "
           f"(hypothesis {r['hypothesis']}, attempt {r['attempt']}); corners "
           + ", ".join(_point_text(c) for c in r["corners"])]
    out.append(f"{ind}  why not split: {r['reason_text']}")
    own = [t for t in r["tests"] if t.get("region_test")]
    other = [t for t in r["tests"] if not t.get("region_test")]
    if own:
        out.append(f"{ind}  its ends and sizes:")
        out += [f"{ind}    {_test_text(t)}" for t in own[:4 * MAX_ITEMS]]
    else:
        out.append(f"{ind}  no END_EVIDENCE or SKU test recorded for it")
    if other:
        out.append(f"{ind}  the other tests of attempt {r['attempt']} ({len(other)}):")
        out += [f"{ind}    {_test_text(t)}" for t in other[:2 * MAX_ITEMS]]
    return out


def format_explanation(d: dict[str, Any]) -> str:
    """The explanation as indented plain text for a terminal."""
    lines = [f"scan {d['scan']} of {d['log']} (alpha {d['alpha']}): "
             f"{_num(d['n_surfaces'])} surface(s)"]
    nz = d.get("noise")
    if nz:
        sig = (f"sigma {_num(nz['sigma_mm'])} mm at {_num(nz['range_m'])} m, "
               if nz.get("sigma_mm") is not None else "")
        lines.append(f"noise model: {nz['source'].lower()}, {sig}row_corr "
                     f"{_num(nz['model']['row_corr'])} ({nz['reason']})")
        if nz.get("fit"):
            lines.append(f"  {_test_text(nz['fit'])}")
        wb = nz.get("worst_bin")
        if wb:
            dof = (f"t with {_num(wb['dof'])} dof" if math.isfinite(wb["dof"])
                   else "normal (a log from before the t)")
            cr, ar, cc, ac = nz.get("tile_correlation") or (0.0, 0.0, 0.0, 0.0)
            lines.append(f"  worst range bin: {_num(wb['range_m'])} m, flat tiles scatter "
                         f"{_num(wb['ratio'])}x the model's sigma ({wb['tiles']} tiles; design "
                         f"effect {_num(wb['design_effect'])}, the tiles' scales correlating "
                         f"{_num(cr)} x {_num(ar)}^k along rows, {_num(cc)} x {_num(ac)}^k "
                         f"along columns; {dof})")
        rate = nz["model"].get("exceed_rate", 0.0)
        if rate > 0:  # measured on the scan (0: the normal's alpha / 2, a pinned model's)
            reach = nz["model"].get("exceed_corr_px", 0.0)
            lines.append(f"  exposure null: {_num(100.0 * rate)} % of a face's points beyond "
                         f"k in front, counts {_num(nz['model'].get('exceed_dispersion', 1.0))}"
                         "x as variable as independent points' (its flat tiles)"
                         + (f", in patches reaching {_num(reach)} px" if reach > 0 else ""))
    for b in d.get("budgets") or []:
        lines.append(f"budget exhausted: the {b['stage']} stage stopped at {_num(b['budget'])} "
                     f"{b['counts']} (it needed {_num(b['work'])}); the scan finished with "
                     "what it had")
    if d.get("pipeline_error"):
        e = d["pipeline_error"]
        lines.append(f"the pipeline failed on this scan: {e.get('error_type')} in "
                     f"{e.get('stage')}: {e.get('message')}")
    if d["mode"] in ("surface", "failed_picks"):
        if not d["surfaces"]:
            lines.append("no failed pick recorded for this scan" if d["mode"] == "failed_picks"
                         else "no surface to explain")
        for e in d["surfaces"]:
            lines.append("")
            lines += _surface_lines(e)
        return "\n".join(lines) + "\n"
    a = d["at"]
    w = a["where"]
    loc = f"pixel (x {w['pixel'][0]}, y {w['pixel'][1]})"
    if w.get("point"):
        loc += f", point {_point_text(w['point'])}"
    lines.append(f"at {loc}")
    if w.get("no_return"):
        lines.append("  no return at that pixel" + (
            f"; using pixel {w['used_pixel']}" if "used_pixel" in w else ""))
    lines.append(f"the chain stopped at: {a['stopped_at'].upper()}")
    lines.append(f"  {a['why']}")
    if "region" in a:
        r = a["region"]
        ext = r.get("extent_mm") or [None, None]
        size = (f" ({_num(ext[0])} x {_num(ext[1])} mm)" if ext[0] is not None else "")
        lines.append(f"  region on the point's plane that no edge crosses: {r['n_pixels']} "
                     f"pixels{size}, bounded by {r['n_boundary_edges']} edge points "
                     f"({_kinds_text(r['boundary_edge_kinds'])})")
    for ln in a.get("lines", [])[:6]:
        lines.append(f"  bounding line {_line_text(ln)}; {ln['boundary_support']} of its "
                     "points bound the region")
    for p in a.get("line_pairs", [])[:6]:
        lines.append(f"  pair L{p['lines'][0]}, L{p['lines'][1]}:")
        lines += [f"    {_test_text(t)}" for t in p["tests"]]
    for v in a.get("vertices", [])[:4] if a["stopped_at"] == "dimensions" else []:
        lines += _vertex_lines(v, "  ")
    for h in a.get("hypotheses", [])[:4] if a["stopped_at"] == "dimensions" else []:
        lines.append(f"  hypothesis {h['id']} of vertex V{h['vertex']['id']}:")
        lines += _dims_lines(h["dimensions"], "    ")
        for at in h["attempts"][:4]:
            lines += _attempt_lines(at, "    ")
    for at in a.get("attempts", [])[:6]:
        lines += _attempt_lines(at, "  ")
    if a.get("ambiguous"):
        lines += _ambiguous_lines(a["ambiguous"], "  ")
    if a.get("explanation"):
        lines.append("")
        lines += _surface_lines(a["explanation"])
    return "\n".join(lines) + "\n"

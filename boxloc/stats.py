"""Statistical tests of uncertain geometric relations and the table that records them.

Every geometric decision in boxloc is a test ``T <= chi2_{r, 1-alpha}`` with one
significance level alpha (Förstner, Brunn & Heuel, DAGM 2000; the paper's ref [3]).
Each stage keeps every test it made in a :class:`TestTable`, so a post-mortem can read the
statistic, the degrees of freedom, the critical value, the p-value and the decision.
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass
from enum import IntEnum
from functools import lru_cache
from typing import Any

import numpy as np
import numpy.typing as npt


def _distributions() -> Any:
    """:mod:`boxloc.distributions`, imported on first use: scipy.special costs ~0.3 s of CPU,
    and the processes that only read products (log readers, ``run --workers``' parent)
    never compute a test."""
    from boxloc import distributions

    return distributions


class TestKind(IntEnum):
    """What a test decided. ``a`` and ``b`` name the entities, as documented per kind."""

    __test__ = False  # not a pytest class

    #: edge stage: a breakpoint is a jump (a = edge-point id or -1, b = scan line)
    JUMP = 1
    #: edge stage: the fold at a breakpoint exceeds min_crease_angle (a = edge point, b = line)
    CREASE = 2
    #: line stage: the line's support passes point-on-line (a = line, b = support size)
    POINT_ON_LINE = 3
    #: vertex stage: two lines meet (a, b = line ids), 1 dof
    LINES_MEET = 4
    #: vertex stage: two lines are orthogonal (a, b = line ids), 1 dof
    LINES_ORTHOGONAL = 5
    #: vertex stage: the intersection lies at an end of both segments (a, b = line ids)
    AT_SEGMENT_ENDS = 6
    #: hypothesis stage: vertex b lies on the plane of hypothesis a's rectangle, 1 dof
    COPLANAR = 7
    #: hypothesis stage: vertex b's directions are parallel to hypothesis a's, 2 dof
    PARALLEL = 8
    #: hypothesis stage: vertex b lies in the first quadrant of hypothesis a (one-sided z)
    FIRST_QUADRANT = 9
    #: hypothesis stage: edge points on hypothesis a's plane (b = number tested), 1 dof each
    POINT_ON_PLANE = 10
    #: hypothesis stage: |P_f| > p (a = hypothesis, statistic = |P_f|, critical = p)
    EDGE_SUPPORT = 11
    #: verification: range points inside hypothesis a that lie on its plane (fraction)
    VERIFY_INLIERS = 12
    #: verification: the mean signed distance of the inliers is zero, 1 dof
    VERIFY_MEAN = 13
    #: verification: no edge crosses the interior of hypothesis a (binomial on edge pixels)
    VERIFY_INTERIOR = 14
    #: verification: hypothesis a's normal is within max_tilt of up (a prior, not chi2)
    VERIFY_TILT = 15
    #: verification: points in front of hypothesis a's face, in its core, are no more than
    #: behind (row 0: sign test, b = points off the plane) or than the noise model's
    #: alpha/2, over the core (row 1: binomial, b = points in the core) and in its busiest
    #: cell (row 2: binomial, Bonferroni over the cells, b = points in the cell); covered
    #: if row 0 rejects and row 1 or row 2 does
    VERIFY_EXPOSED = 16
    #: verification: the sides of hypothesis a are lines of convex edge points (rows 0-3:
    #: distinct positions covered per side, critical = MIN_LINE_POINTS or the side's
    #: concave-crease count if larger; row 4: the perimeter fraction covered, critical p)
    VERIFY_BOUNDARY = 17
    #: verification: a side of hypothesis a with no line of boundary edges, or beyond which
    #: the face's plane continues, is a seam (or, in the latter case, a gap) (b = side 0-3:
    #: v=0, v=length, u=0, u=width; statistic z, one-sided)
    VERIFY_SEAM_SIDE = 18
    #: verification: no seam crosses the interior of hypothesis a (b = 0 along x, 1 along
    #: y; statistic = the largest z inside)
    VERIFY_SEAM_INTERIOR = 19
    #: hypothesis stage: seams in vertex a's region, extra dimension candidates (b = 0
    #: along x, 1 along y; 2, 3 likewise in the last short box edge before max_edge; one
    #: row per seam found, statistic z)
    SEAM_PEAK = 20
    #: verification: the face's plane ends at side b of hypothesis a (b = side 0-3;
    #: statistic = fraction of the pixels just beyond the side on the plane, critical =
    #: min_inlier_fraction), or the side is a seam (a VERIFY_SEAM_SIDE row); a side whose
    #: strip leaves the image is not accepted (the face may run on out of sight)
    VERIFY_CONTINUATION = 21
    #: hypothesis stage: how far vertex a's plane runs along arm b (0 = x, 1 = y):
    #: statistic = the extent, critical = the gap that ends it (metres); accepted if the
    #: extent is a box edge (min_edge to max_edge) and so a far-side candidate
    FACE_EXTENT = 22
    #: hypothesis stage: a corner of verified hypothesis a's seam side, where a touching
    #: neighbour of equal height has a corner too, is known: vertex b's verified rectangle
    #: covers its quadrant (statistic 0), or vertex b of the same quadrant coincides with
    #: it (statistic = chi2 of the positions, 3 dof; b = -1 if there is none); rejected
    #: means a new vertex (``VertexSet.parent``)
    NEIGHBOUR_CORNER = 23
    #: verification: no seam side of verified attempt b crosses the core of verified
    #: attempt a (statistic = the fraction of that side inside a's core, beyond
    #: BOUNDARY_BAND min_edge of its sides and on its plane; critical 0.5): a seam shown at
    #: a known place is stronger evidence than a search for one anywhere inside
    VERIFY_SEAM_CROSSING = 24
    #: result stage: the lid of chosen attempt a is flat: its rim-supported bulge term is
    #: zero (:func:`boxloc.stages.surfaces.fit_bulge`; statistic (k / sigma_k)^2, 1 dof); rejected
    #: puts the surface's centre on the rim's plane
    SURFACE_BULGE = 25
    #: vertex stage: the box corner at vertex a's convex-crease arm (b = the crease line)
    #: can be a top's: the face across the crease is within max_tilt of up (statistic =
    #: (cos max_tilt - n.up) / sigma, one-sided z); accepted adds its vertex
    BOX_CORNER = 26
    #: edge stage: a scan line's first or last return is followed by no return out to the
    #: image border (a = edge point, b = pixel; statistic = the no-return run, pixels;
    #: critical = NO_RETURN_PX): the surface ends there, a jump with no far side
    NO_RETURN = 27
    #: noise stage: the noise model in use predicts the scale of the scan's flat-tile
    #: residuals within the margin that doubles a 1-dof test's rate at alpha (ln 0.102 at
    #: 0.01): per range bin, z_b = (|mean over its tiles of ln(tile std / model std)| -
    #: margin) / its standard error from the tiles' spread; statistic = the largest z_b,
    #: critical = the one-sided normal quantile at alpha / bins (a = -1, b = bins)
    NOISE_FIT = 28
    #: a stage stopped at its work budget (a = the stage: 1 lines, 2 hypotheses; statistic
    #: = the work it needed, or did when stopped; critical = the budget; always rejected:
    #: a row only where it was hit) and the scan finished with what it had. Lines count the
    #: neighbour points their Hough trials examined, hypotheses the vertices worked on
    #: (the highest first). Counted in work, not seconds, so a replay stops where the run
    #: did.
    BUDGET = 29
    #: result stage: the dimensions of attempt a's rectangle match listed carton size b
    #: (``Config.box_sizes`` row; -1: no list, the nearest otherwise): statistic =
    #: ((w - W)^2 + (l - L)^2) / size_tolerance^2 for the nearer of the two orientations,
    #: 2 dof, chi2(2) at alpha; rejected for every listed size flags the box
    SKU_SIZE = 30
    #: hypothesis stage: the seam a carton size implies inside a flat region, however weak:
    #: in the region's rows (a = its attempt) b = the cut (x cuts first, then y), in the
    #: rows of each part's verification (a = the part's attempt) b = its side 0-3 that is
    #: a cut; statistic = the groove z there, critical = the seam level's z; accepted
    #: where the seam is seen. The region is split on the size's evidence whatever the
    #: rows say; they record how much the range points back it
    SKU_SPLIT_SEAM = 31
    #: hypothesis stage: side b (0-3: v=0, v=length, u=0, u=width) of attempt a has evidence
    #: of the box's end: statistic = the evidence (0 none, 1 a line of jump or convex-crease
    #: edges, 2 a groove or seam, 3 a listed size's implied seam, 4 the outline of the
    #: verified flat region a part of a split lies on, 5 the face's plane dropping away
    #: beyond it); critical 1; accepted if any
    END_EVIDENCE = 32
    #: result stage: the height of chosen attempt a's box (b = :class:`boxloc.products.
    #: HeightSource`): statistic = the height, metres; critical = its standard deviation,
    #: metres; accepted where the height is significant (> z at alpha sigmas). Hypothesis
    #: stage, in a flat region's rows: the smallest step down beyond its sides (b = STEP)
    #: against the listed height of the carton it would be split into (critical = that
    #: height less z at alpha of both uncertainties); rejected leaves it unsplit
    BOX_HEIGHT = 33
    #: verification: side b (0-3) of hypothesis a, without a line of boundary edges or a
    #: seam, ends where the face's refitted plane ends just beyond it: statistic = the
    #: fraction of the valid pixels of the strip beyond the side on the plane, critical =
    #: PLANE_END_FRACTION; accepted counts the side as a boundary (a fold or step the scan
    #: lines did not resolve)
    VERIFY_PLANE_END = 34
    #: hypotheses: vertex a's plane (the normal of its two lines) is within ``max_tilt`` of
    #: up: statistic = its tilt, radians; critical = ``max_tilt``. Recorded where it is not:
    #: no rectangle is sought from that vertex, since every one would share its normal and
    #: fail VERIFY_TILT (a side face of a stack, seen from above at an angle)
    HYPOTHESIS_TILT = 35
    #: result stage: chosen attempt a's box lies in one flush layer with attempt b's (their
    #: tops touch and are coplanar), and b's side-face height is the layer's smallest:
    #: statistic = a's own measured height less b's, over the sigma of that difference
    #: (+inf: a measured none); critical = z at alpha. Accepted takes b's height for a:
    #: a's own reached significantly deeper (down a stack's side, to the floor beyond it)
    LAYER_HEIGHT = 36
    #: hypothesis stage, in a flat region's rows: its split's grid is the only way to lay
    #: the listed cartons over the grid's extent (:func:`boxloc.stages.sizes.other_tiling`;
    #: b = the grid's listed size): statistic = the cartons laid otherwise (turned, or of
    #: another size) in the first other tiling found, 0 if none, NaN where the search
    #: stopped at its budget (``sizes.MAX_TILING_STATES`` skylines) undecided; critical 0.
    #: Rejected: seams seen at every cut of a grid show it is the grid (their SKU_SPLIT_SEAM
    #: rows), seams seen along every inner carton side of one tiling show that one
    #: (SKU_SEEN_TILING); else the region stays unsplit (``SEVERAL_TILINGS``)
    SKU_TILING = 37
    #: verification: a seam crosses verified attempt a's interior where a side of verified
    #: attempt b, which touches it, runs on into it (a flush neighbour's seam continuing
    #: straight across two merged tops): the groove z along that whole line of a's points
    #: (both halves), over its spread along a; critical = z at alpha over the lines a is
    #: tested at. Accepted where no seam is seen; rejected rejects a (``INTERIOR_SEAM``)
    VERIFY_SEAM_IN_LINE = 38
    #: hypothesis stage, in a flat region's rows, where its grid is not the only tiling of
    #: its outline (SKU_TILING rejected): the tilings by the listed cartons whose every
    #: carton side inside the region shows a seam (:func:`boxloc.stages.sizes.
    #: seen_tilings`; b = the cartons laid otherwise than the grid in the first one, -1 if
    #: none): statistic = how many (2: two or more; NaN where the search stopped at its
    #: budget), critical 1. Accepted for exactly one: the region is split into it, its
    #: sides' grooves in SKU_SPLIT_SEAM rows after the grid's cuts; else ``SEVERAL_TILINGS``
    SKU_SEEN_TILING = 39
    #: verification: attempt a's face does not run on under something thin lying beyond
    #: side b (b = side 0-3): statistic = the fraction of the strip beyond the side (the
    #: VERIFY_CONTINUATION strip) in front of the plane; critical ``RAISED_FRACTION``.
    #: Rejected where at least that much is, no higher than the flatness prior (the
    #: strip's median height at most k ``flatness``), and the side is no seam: the edge
    #: of tape or a label on the lid is no end of the face (reason ``CONTINUES``)
    VERIFY_RAISED_BEYOND = 40
    #: verification: how high the strip beyond side b of attempt a stands (b = side 0-3,
    #: one row per VERIFY_RAISED_BEYOND row): statistic = the median height of the strip's
    #: points above the face's plane (metres, along its normal; NaN without points, then
    #: not accepted), critical = k ``flatness``. Accepted where no higher: nothing beyond
    #: stands taller than tape or a label could (a drop to the floor is accepted too);
    #: VERIFY_RAISED_BEYOND needs that, with its front fraction, to reject the side
    VERIFY_RAISED_HEIGHT = 41
    #: verification: no seams where attempt a's face would have them were it n equal
    #: boxes in a row along axis b % 2, n = b // 2 + 2 (b 0: the line u = width / 2, 1:
    #: v = length / 2; 2, 3: the thirds along u, v; 4, 5: the quarters), tested where each
    #: part could be a box (at least ``MIDLINE_HALF`` ``min_edge``; with a carton list, a
    #: listed size): statistic = the lines' groove z summed over sqrt(n - 1) (NaN: no
    #: points), critical = Bonferroni z at alpha over the few positions tried. Rejected:
    #: n boxes side by side (reason ``INTERIOR_SEAM``)
    VERIFY_SEAM_MIDLINE = 42
    #: height: a measurement of attempt a's box height reaches deeper than any carton is
    #: tall (b = the side 0-3 of a side face, 4 + the side of a step): statistic = the
    #: measured height, metres; critical = ``max_edge`` (the longest edge of any box, a site
    #: fact) plus z at alpha of the measurement's sigma. Only rejected rows are recorded: the
    #: measurement is a flush stack's side or the drop to the floor beyond the pallet, not
    #: this box's height, and is not used
    HEIGHT_WITHIN_BOX = 43
    #: height: attempt a's measured height (b = its source) agrees with its matched
    #: carton's listed height: statistic = chi2 of their difference over the measurement's
    #: variance plus the size tolerance squared (1 dof). Accepted: the two are combined,
    #: each weighed by its variance, and the source kept; rejected: the measurement is not
    #: this carton's (a stack's side, the floor beyond), and the listed height replaces it
    HEIGHT_SKU_AGREEMENT = 44
    #: hypothesis stage, with a carton list, at vertex a's flat region that did not
    #: verify whole: the listed cartons lining its side along arm b (0 = x, 1 = y), seen
    #: from the corner to the region's end (:func:`boxloc.stages.sizes.row_cartons`):
    #: statistic = the ways listed edges add up to the side's length (2: two or more; NaN
    #: where the search stopped at its budget), critical 1. Accepted where exactly one way
    #: of one edge, of one depth: a ROW attempt of those cartons is verified
    SKU_ROW = 45
    #: hypothesis stage, with a carton list, right after an accepted SKU_ROW row of
    #: vertex a whose depth the region reaches: the side ends at a corner that was seen,
    #: the vertex nearest the side's end whose arms run back along the side and on along
    #: a's other arm (b = that vertex, -1 if none, then statistic inf): statistic = chi2
    #: (2 dof) of its position in a's plane against the side's end, over both corners'
    #: covariances plus the row's length tolerance (n ``size_tolerance``^2 along the
    #: side); critical at alpha. Rejected: no ROW (the side may end at the image's border,
    #: or on noise)
    ROW_END = 46
    #: hypothesis stage, at the end: verified rectangle a (an attempt) against the verified
    #: rectangle b (an attempt) in its plane that it is the best multiple of: statistic =
    #: chi2 (2 dof) of its sides (p, q) against b's (u, n v), n = round(q / v) >= 2, over
    #: ``size_tolerance`` per measured side; critical at alpha. Accepted: a is n of b, and
    #: is left ambiguous (``MULTIPLE_OF_A_NEIGHBOUR``), not reported
    REPEATS_NEIGHBOUR = 47
    #: hypothesis stage, without a carton list: a carton size the scan shows, the size of
    #: verified box a (an attempt) that a rectangle beside it repeats (REPEATS_NEIGHBOUR
    #: accepted with b = a) or that lies beside a flat region left ambiguous: statistic =
    #: the verified boxes of that size (each side within ``size_tolerance``) apart from
    #: one another (centres more than half its short side apart), critical 2. Accepted: b
    #: is its index in the scan's own carton list, by which the flat regions are then
    #: split as by a listed one (SEEN_SPLIT parts; the SKU_* rows' b index it); rejected
    #: (b = -1): one box of a size is no list
    SEEN_CARTON = 48


#: ``TestKind.BUDGET`` rows' ``a``: the stage whose budget it is.
BUDGET_LINES = 1
BUDGET_HYPOTHESES = 2
#: the hypothesis stage's pixels read (``Config.max_hypothesis_work``)
BUDGET_HYPOTHESIS_WORK = 3
#: the edge stage's samples visited by the split-and-merge (``Config.max_edge_work``)
BUDGET_EDGES = 4

#: How a row's statistic stands to its critical value where the numbers alone accept it:
#: ``"<="`` for a chi-square test (the default), the other way for a detection or a count
#: that must reach a bound. None where the two are not compared (a summary count, a range
#: check: see the kind's comment). Post-mortem text prints the relation the numbers show,
#: never one inferred from the decision.
RELATION: dict[TestKind, str | None] = {
    TestKind.JUMP: ">", TestKind.CREASE: ">", TestKind.NO_RETURN: ">=",
    TestKind.EDGE_SUPPORT: ">", TestKind.FIRST_QUADRANT: ">",
    TestKind.POINT_ON_PLANE: None, TestKind.FACE_EXTENT: None,
    TestKind.VERIFY_INLIERS: ">=", TestKind.VERIFY_BOUNDARY: ">=",
    TestKind.VERIFY_INTERIOR: "<",
    TestKind.VERIFY_SEAM_SIDE: ">", TestKind.SEAM_PEAK: ">",
    TestKind.VERIFY_CONTINUATION: "<", TestKind.VERIFY_SEAM_CROSSING: "<",
    TestKind.END_EVIDENCE: ">=", TestKind.SKU_SPLIT_SEAM: ">", TestKind.BOX_HEIGHT: ">",
    TestKind.BUDGET: "<", TestKind.LAYER_HEIGHT: ">", TestKind.VERIFY_SEAM_IN_LINE: "<=",
    TestKind.SKU_SEEN_TILING: None, TestKind.VERIFY_RAISED_BEYOND: "<",
    TestKind.VERIFY_RAISED_HEIGHT: "<=", TestKind.VERIFY_SEAM_MIDLINE: "<=",
    TestKind.HEIGHT_WITHIN_BOX: "<=", TestKind.SEEN_CARTON: ">=",
}

_RELATION_OPS = {"<=": operator.le, "<": operator.lt, ">": operator.gt, ">=": operator.ge}


def numbers_accept(kind: TestKind, statistic: float, critical: float) -> bool | None:
    """Whether a row's statistic and critical value alone accept it, by :data:`RELATION`;
    None where the kind does not compare them or either is not finite (the decision then
    rests on the kind's own rule)."""
    rel = RELATION.get(kind, "<=")
    s, c = float(statistic), float(critical)
    if rel is None or not (math.isfinite(s) and math.isfinite(c)):
        return None
    return bool(_RELATION_OPS[rel](s, c))


#: The kinds whose decision has conditions beyond :data:`RELATION`: why a row is accepted
#: against its numbers, and why one is rejected against them ("" where that cannot happen).
FURTHER_CONDITIONS: dict[TestKind, tuple[str, str]] = {
    TestKind.VERIFY_BOUNDARY: ("", "the line is not significant over the interior's "
                                   "scattered edges (p >= alpha)"),
    TestKind.VERIFY_INTERIOR: ("the line is not significant (p >= the interior's alpha) "
                               "or too short", ""),
    TestKind.VERIFY_CONTINUATION: ("the side is a seam or a gap (VERIFY_SEAM_SIDE)",
                                   "the side's strip leaves the image"),
    TestKind.VERIFY_PLANE_END: ("", "points in front of the plane, or the strip out of the "
                                    "image"),
    TestKind.BOX_HEIGHT: ("", "under z at alpha times its sigma"),
    TestKind.VERIFY_RAISED_BEYOND: ("the strip stands higher than the flatness prior (a "
                                    "taller box beyond: VERIFY_RAISED_HEIGHT rejected), or "
                                    "the side is a seam", ""),
}


@lru_cache(maxsize=256)
def chi2_critical(dof: float, alpha: float) -> float:
    """Critical value ``chi2_{dof, 1-alpha}``."""
    return float(_distributions().chi2_ppf(1.0 - alpha, dof))


def nanmedian_last(a: np.ndarray) -> np.ndarray:
    """``np.nanmedian(a, axis=-1)``, bit for bit, by one sort.

    NumPy takes a masked-array path for a NaN median along a short axis (under 600 values),
    about ten times slower than sorting: the noise stage's tiles and the edge stage's
    local scale take medians over thousands of 256- and 512-value rows per scan. The
    median is the middle order statistic of the non-NaN values, or the mean of the two
    middle ones, ``(lo + hi) / 2`` as NumPy computes it; NaN where a row has none.

    Parameters
    ----------
    a : (..., n) float64

    Returns
    -------
    (...,) float64
    """
    a = np.asarray(a, dtype=np.float64)
    s = np.sort(a, axis=-1)  # NaN last
    n = np.count_nonzero(~np.isnan(a), axis=-1)
    lo = np.take_along_axis(s, np.maximum((n - 1) // 2, 0)[..., None], -1)[..., 0]
    hi = np.take_along_axis(s, np.maximum(n // 2, 0)[..., None], -1)[..., 0]
    with np.errstate(invalid="ignore"):
        mid = np.where(n % 2 == 1, lo, (lo + hi) / 2.0)
    return np.where(n > 0, mid, np.nan)


def half_normal_sigma(x: np.ndarray, alpha: float,
                      max_iter: int = 50) -> tuple[float, np.ndarray, float]:
    """Robust sigma of the half-normal part of magnitudes ``x`` among a broad background.

    The median of |N(0, sigma)| is 0.6745 sigma; the estimate is iterated on the values
    within the two-sided critical value at alpha until it no longer changes.

    Returns
    -------
    sigma : float
    kept : (n,) bool
        The values within ``k * sigma``.
    k : float
        The two-sided critical value (z at alpha / 2).
    """
    x = np.asarray(x, dtype=np.float64)
    med = float(_distributions().halfnorm_ppf(0.5))
    k = float(_distributions().norm_isf(alpha / 2.0))
    sigma = float(np.median(x)) / med
    kept = np.ones(len(x), bool)
    for _ in range(max_iter):
        kept = x <= k * sigma
        new = float(np.median(x[kept])) / med
        if abs(new - sigma) <= 1e-9:
            break
        sigma = new
    return sigma, kept, k


def chi2_test(
    statistic: npt.ArrayLike, dof: float, alpha: float
) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """Vectorized chi-square test.

    Returns
    -------
    statistic : ndarray, float64
    critical : float
    p_value : ndarray, float64
    accepted : ndarray, bool
        True where the relation holds: ``statistic <= critical``.
    """
    t = np.asarray(statistic, dtype=np.float64)
    crit = chi2_critical(float(dof), float(alpha))
    p = _distributions().chi2_sf(t, dof)
    return t, crit, np.asarray(p, dtype=np.float64), t <= crit


def float32_precision(a: npt.ArrayLike) -> np.ndarray:
    """``a`` as float64 rounded to the nearest float32 (NaN, infinities and -0.0 kept).

    For products whose last digits carry nothing: values derived from a float32 range image
    (edge points), noise-model covariances, p-values (decisions compare the statistic with
    its critical value, never the p-value). Seven significant digits are kept, and a log
    stores such an array in half the bytes (:mod:`recorder.mcap.encode`, filters 6 and 7).
    Values beyond float32's range become infinite; p-values below 1e-45 become 0.
    """
    with np.errstate(over="ignore"):
        return np.asarray(a, np.float64).astype(np.float32).astype(np.float64)


_COLUMNS = ("kind", "a", "b", "statistic", "dof", "critical", "p_value", "accepted")


def _column(x: npt.ArrayLike, dtype: Any, n: int) -> np.ndarray:
    """``np.broadcast_to(np.asarray(x, dtype), (n,)).copy()``, without broadcast_to's cost
    for the two common cases (a scalar, an array of n): tests are recorded by the thousand
    per scan, a few values each."""
    v = np.asarray(x, dtype)
    if v.shape == (n,):
        return v.copy()
    if v.ndim == 0:
        return np.full(n, v, dtype)
    return np.broadcast_to(v, (n,)).copy()


@dataclass(frozen=True, eq=False)
class TestTable:
    """A column table of statistical tests.

    Attributes
    ----------
    kind : ndarray (n,), uint8
        :class:`TestKind` of each test.
    a, b : ndarray (n,), int32
        The entities tested (meaning per kind; -1 when unused).
    statistic : ndarray (n,), float64
    dof : ndarray (n,), float32
        Degrees of freedom (0 for decisions that are not chi-square tests).
    critical : ndarray (n,), float64
    p_value : ndarray (n,), float64
        NaN for decisions that are not chi-square tests. To float32 precision
        (:func:`float32_precision`) where the table was made by :meth:`chi2` or
        :meth:`decision`.
    accepted : ndarray (n,), bool
        The decision: True where the relation was accepted.
    alpha : float
        The significance level of every test in the table.
    """

    __test__ = False

    kind: np.ndarray
    a: np.ndarray
    b: np.ndarray
    statistic: np.ndarray
    dof: np.ndarray
    critical: np.ndarray
    p_value: np.ndarray
    accepted: np.ndarray
    alpha: float

    def __len__(self) -> int:
        return int(self.kind.shape[0])

    @classmethod
    def empty(cls, alpha: float) -> TestTable:
        return cls(
            kind=np.zeros(0, np.uint8), a=np.zeros(0, np.int32), b=np.zeros(0, np.int32),
            statistic=np.zeros(0), dof=np.zeros(0, np.float32), critical=np.zeros(0),
            p_value=np.zeros(0), accepted=np.zeros(0, bool), alpha=float(alpha),
        )

    @classmethod
    def chi2(
        cls,
        kind: TestKind,
        a: npt.ArrayLike,
        b: npt.ArrayLike,
        statistic: npt.ArrayLike,
        dof: float,
        alpha: float,
    ) -> TestTable:
        """Run chi-square tests and record them."""
        t, crit, p, acc = chi2_test(statistic, dof, alpha)
        t = np.atleast_1d(t)
        n = t.shape[0]
        return cls(
            kind=np.full(n, int(kind), np.uint8),
            a=_column(a, np.int32, n),
            b=_column(b, np.int32, n),
            statistic=t,
            dof=np.full(n, dof, np.float32),
            critical=np.full(n, crit),
            p_value=float32_precision(np.atleast_1d(p)),
            accepted=np.atleast_1d(acc),
            alpha=float(alpha),
        )

    @classmethod
    def decision(
        cls,
        kind: TestKind,
        a: npt.ArrayLike,
        b: npt.ArrayLike,
        statistic: npt.ArrayLike,
        critical: npt.ArrayLike,
        accepted: npt.ArrayLike,
        alpha: float,
        p_value: npt.ArrayLike | float = np.nan,
        dof: float = 0.0,
    ) -> TestTable:
        """Record decisions that are not plain chi-square tests (supports, fractions, priors)."""
        s = np.atleast_1d(np.asarray(statistic, np.float64))
        n = s.shape[0]
        return cls(
            kind=np.full(n, int(kind), np.uint8),
            a=_column(a, np.int32, n),
            b=_column(b, np.int32, n),
            statistic=s,
            dof=np.full(n, dof, np.float32),
            critical=_column(critical, np.float64, n),
            p_value=float32_precision(_column(p_value, np.float64, n)),
            accepted=_column(accepted, bool, n),
            alpha=float(alpha),
        )

    @classmethod
    def concat(cls, tables: list[TestTable], alpha: float) -> TestTable:
        tables = [t for t in tables if len(t)]
        if not tables:
            return cls.empty(alpha)
        return cls(
            **{
                name: np.concatenate([getattr(t, name) for t in tables])
                for name in _COLUMNS
            },
            alpha=float(alpha),
        )

    def select(self, mask: npt.ArrayLike) -> TestTable:
        m = np.asarray(mask)
        return TestTable(
            **{
                name: getattr(self, name)[m]
                for name in _COLUMNS
            },
            alpha=self.alpha,
        )

    @classmethod
    def budget(cls, stage: int, work: int, budget: int, exhausted: bool,
               alpha: float) -> TestTable:
        """A stage's BUDGET row where it stopped at its budget; none where it did not (so
        a scan's products are those of a run without budgets unless one was hit)."""
        if not exhausted:
            return cls.empty(alpha)
        return cls.decision(TestKind.BUDGET, stage, -1, float(work), float(budget), False,
                            alpha)

    def of_kind(self, kind: TestKind) -> TestTable:
        return self.select(self.kind == int(kind))

    def rows(self) -> list[dict[str, object]]:
        """The tests as plain dicts (for reports and JSON)."""
        return [
            {
                "kind": TestKind(int(k)).name, "a": int(a), "b": int(b), "statistic": float(s),
                "dof": float(d), "critical": float(c), "p_value": float(p),
                "alpha": self.alpha, "accepted": bool(acc),
            }
            for k, a, b, s, d, c, p, acc in zip(
                self.kind, self.a, self.b, self.statistic, self.dof, self.critical,
                self.p_value, self.accepted,
            )
        ]

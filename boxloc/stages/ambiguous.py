"""Flat regions the evidence cannot split into boxes (issue #21, point 1).

A tightly packed layer of cartons of equal height with sharp edges and no gaps shows no
seam between them: their tops are one flat region. Reporting a rectangle over several
tops would make the robot grip two cartons and drop them; reporting a sliver of one is
as wrong. So a flat region larger than a box (``max_edge``) that verifies as a whole (each
side ends with evidence, nothing crosses it; :func:`boxloc.stages.hypotheses.
dimensions_from_region`) is not a surface. With a carton list it is split at the seams
a listed size implies; otherwise, or where no split or more than one fits, it is
*ambiguous*: listed with its outline, area, reason and the tests behind it, so the cell
can fall back (push, re-scan, ask an operator).

:func:`ambiguous_regions` collects them from the hypothesis and verification products;
it decides nothing itself.
"""

from __future__ import annotations

import numpy as np

from boxloc.config import Config
from boxloc.products import (
    AmbiguityReason,
    AmbiguousSet,
    DimensionSource,
    HypothesisSet,
    Verification,
    VerifyReason,
)
from boxloc.stages.verify import rectangle_corners
from boxloc.stats import TestKind, TestTable

#: The verification rows behind an ambiguous region, in the JSON and the log: what shows
#: its sides end, that nothing splits it, and what the carton list said.
REGION_TEST_KINDS = (TestKind.VERIFY_INTERIOR, TestKind.VERIFY_BOUNDARY,
                     TestKind.VERIFY_SEAM_SIDE, TestKind.VERIFY_SEAM_INTERIOR,
                     TestKind.VERIFY_CONTINUATION, TestKind.VERIFY_PLANE_END, TestKind.SKU_SIZE,
                     TestKind.SKU_SPLIT_SEAM, TestKind.SKU_TILING, TestKind.SKU_SEEN_TILING,
                     TestKind.BOX_HEIGHT, TestKind.REPEATS_NEIGHBOUR)

#: END_EVIDENCE's statistic: the evidence of a side's end.
EVIDENCE_NONE, EVIDENCE_EDGES, EVIDENCE_SEAM, EVIDENCE_SIZE, EVIDENCE_REGION = 0, 1, 2, 3, 4
#: the face's plane drops away just beyond the side (VERIFY_PLANE_END): a jump or crease
#: the scan lines did not resolve
EVIDENCE_PLANE_END = 5


def end_evidence(tests: TestTable, attempt: int, part: bool = False) -> TestTable:
    """END_EVIDENCE rows of one attempt's four sides, from its verification rows: a line
    of jump or convex-crease edges (VERIFY_BOUNDARY rows 0-3), else a groove or seam
    (VERIFY_SEAM_SIDE), else the plane dropping away beyond it (VERIFY_PLANE_END), else,
    for a ``part`` of a split region, a listed size's implied
    seam (its SKU_SPLIT_SEAM rows, b = side), else the region's verified outline it lies
    on; statistic the evidence, critical 1, accepted if any."""
    ev = np.zeros(4)
    b = tests.of_kind(TestKind.VERIFY_BOUNDARY)
    for si in range(min(4, len(b))):
        if b.accepted[si]:
            ev[si] = EVIDENCE_EDGES
    s = tests.of_kind(TestKind.VERIFY_SEAM_SIDE)
    for si, ok in zip(s.b, s.accepted):
        if ok and 0 <= si < 4 and ev[si] == EVIDENCE_NONE:
            ev[si] = EVIDENCE_SEAM
    pe = tests.of_kind(TestKind.VERIFY_PLANE_END)
    for si, ok in zip(pe.b, pe.accepted):
        if ok and 0 <= si < 4 and ev[si] == EVIDENCE_NONE:
            ev[si] = EVIDENCE_PLANE_END
    z = tests.of_kind(TestKind.SKU_SPLIT_SEAM) if part else tests.select(np.zeros(len(tests),
                                                                                  bool))
    for si in z.b:
        if 0 <= si < 4 and ev[si] == EVIDENCE_NONE:
            ev[si] = EVIDENCE_SIZE
    if part:
        ev[ev == EVIDENCE_NONE] = EVIDENCE_REGION
    return TestTable.decision(TestKind.END_EVIDENCE, attempt, np.arange(4), ev, 1.0, ev >= 1,
                              tests.alpha)


#: A region whose points the reported surfaces explain at least this share of is resolved
#: (its boxes were found by their own evidence): not ambiguous. Half: most of it.
RESOLVED_SHARE = 0.5


def ambiguous_regions(hypotheses: HypothesisSet, verification: Verification,
                      config: Config, chosen: np.ndarray | None = None) -> AmbiguousSet:
    """The flat regions not reported as surfaces and not split into them.

    Parameters
    ----------
    hypotheses : HypothesisSet
        REGION attempts carry the outcome of the split in ``att_support`` (parts; 0 not
        split, -1 a duplicate of another region) and ``att_threshold`` (the
        :class:`boxloc.products.AmbiguityReason`).
    verification : Verification
        The regions' outcome (``VerifyReason.AMBIGUOUS``), refitted planes and tests.
    config : Config
    chosen : (s,) int, optional
        The attempts reported as surfaces: a region whose inliers they explain for at
        least ``RESOLVED_SHARE`` is left out.

    Returns
    -------
    AmbiguousSet
        One row per region, in attempt order; its tests are the region's verification
        rows of :data:`REGION_TEST_KINDS`, its FACE_EXTENT rows, and END_EVIDENCE per
        side, all with ``a`` = the region's attempt.
    """
    H = hypotheses
    js = [j for j in range(H.n_attempts)
          if H.att_source[j] == DimensionSource.REGION
          and verification.reason[j] == VerifyReason.AMBIGUOUS and H.att_support[j] == 0]
    if chosen is not None and len(chosen) and js:
        found = np.unique(np.concatenate([verification.inliers_of(int(j)) for j in chosen]))
        js = [j for j in js
              if np.isin(verification.inliers_of(j), found).mean() < RESOLVED_SHARE]
    K = len(js)
    corners = np.zeros((K, 4, 3))
    area, width, length = np.zeros(K), np.zeros(K), np.zeros(K)
    reason = np.zeros(K, np.int8)
    hyp = np.zeros(K, np.int64)
    tables = []
    for k, j in enumerate(js):
        h = int(H.att_hypothesis[j])
        w, ln = float(H.att_width[j]), float(H.att_length[j])
        c = rectangle_corners(H.origins[h], H.x_axis[h], H.y_axis[h], w, ln)
        # on the plane refitted to the region's points
        n, p0 = verification.plane_normals[j], verification.plane_centers[j]
        if np.isfinite(n).all():
            c = c - ((c - p0) @ n)[:, None] * n
        corners[k], area[k] = c, w * ln
        width[k], length[k] = min(w, ln), max(w, ln)
        r = H.att_threshold[j]
        reason[k] = int(r) if np.isfinite(r) else int(AmbiguityReason.NO_END_EVIDENCE)
        hyp[k] = h
        t = verification.tests
        mine = t.select((t.a == j) & np.isin(t.kind, [int(x) for x in REGION_TEST_KINDS]))
        ext = H.tests.select((H.tests.kind == TestKind.FACE_EXTENT) & (H.tests.a == h)
                             & (H.tests.b >= 2))
        ext = TestTable(kind=ext.kind, a=np.full(len(ext), j, np.int32), b=ext.b,
                        statistic=ext.statistic, dof=ext.dof, critical=ext.critical,
                        p_value=ext.p_value, accepted=ext.accepted, alpha=ext.alpha)
        tables += [ext, mine, end_evidence(t.select(t.a == j), j)]
    return AmbiguousSet(hypothesis=hyp, attempt=np.asarray(js, np.int64).reshape(K),
                        corners=corners, area=area, width=width, length=length,
                        reason=reason, tests=TestTable.concat(tables, config.alpha))

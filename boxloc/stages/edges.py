"""Stage 2: edges of the range image by scan-line approximation.

Every row and every column of the organized cloud is approximated by 3D line segments
(split-and-merge, Jiang & Bunke 1999). A scan line crossing a planar face is straight in
3D, so a breakpoint between two segments is where the surface changes:

* **jump** — the two fitted lines are separated along the rays at the break (a depth
  discontinuity); the edge point lies on the nearer line, half a sample past its last point;
* **crease** — the lines meet at an angle of at least ``min_crease_angle``; the edge point
  is their intersection (closest approach), convex or concave as seen from the sensor;
* **groove** — the lines are continuous and collinear but the samples between them lie
  significantly behind both (the seam between two touching boxes of equal height); or,
  inside one segment, a short run of samples lies behind its line with the samples around
  it back on the line, and the deepest of them passes the single-sample test;
* **no-return border** — the scan line's first or last return is followed by no return
  out to the image border, over at least :data:`NO_RETURN_PX` pixels: nothing was measured
  beyond the surface (out of range, a background removed, the sky), so it ends there, a
  jump with no far side to test against (PCL's ``NAN_BOUNDARY``). Labelled a jump, and
  recorded as a decision on the run's length (``TestKind.NO_RETURN``). No return with a
  return beyond it is left to the jump test across the gap.

No segment spans a range step (successive samples at significantly different ranges, the
surface not resuming within a few samples): a total least-squares line through a far step
runs along the rays and would fit both sides (:func:`_split_at_steps`).

Each edge point carries a covariance: the sensor noise at the point plus the localization
uncertainty along the scan line. Where a row scan and a column scan find an edge at the
same pixel, the two estimates are fused (information-weighted).

Thresholds are statistical at the one significance level alpha: a segment is a line if its
largest normalized residual passes a Bonferroni-corrected two-sided z test; a break is a
jump if the gap between the lines fails a chi2(1) continuity test.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from boxloc.calibrate.noise import _least_after, _select
from boxloc.config import Config
from boxloc.distributions import chi2_sf, norm_isf
from boxloc.kernels import kernel
from boxloc.products import EdgeKind, EdgeMap
from boxloc.scan import Scan
from boxloc.stats import (
    BUDGET_EDGES,
    TestKind,
    TestTable,
    chi2_critical,
    float32_precision,
)

#: A groove is a run of this many to GROOVE_MAX_RUN samples behind the line, with
#: GROOVE_CONTEXT samples on the line on each side (a seam, not a trend such as bulge).
GROOVE_MIN_RUN = 2
GROOVE_MAX_RUN = 8
GROOVE_CONTEXT = 4
#: Samples off a surface that resumes at its level after them, at most this many (a groove
#: at most), are no range step (:func:`_split_at_steps`).
STEP_RUN_MAX = GROOVE_MAX_RUN

#: Segments with fewer samples are not fitted (their samples are "dropped": mixed pixels,
#: a sliver of a steep side face). Three is the fewest that can show a line's residual.
MIN_SEGMENT_POINTS = 4


#: No return over at least this many pixels, out to the image border, ends a surface (a
#: no-return-border jump); shorter runs are dropouts inside a face (as
#: :data:`boxloc.stages.verify.EXTENT_GAP_PX`, 4, the longest a face's extent bridges).
NO_RETURN_PX = 5


# --- kernels -------------------------------------------------------------------------------


@kernel
def _fit(P: np.ndarray, s: int, e: int) -> tuple[np.ndarray, np.ndarray]:
    """Total-least-squares line through P[s:e+1]: centroid, unit direction (s -> e)."""
    n = e - s + 1
    cx = cy = cz = 0.0
    for i in range(s, e + 1):
        cx += P[i, 0]
        cy += P[i, 1]
        cz += P[i, 2]
    cx /= n
    cy /= n
    cz /= n
    sxx = sxy = sxz = syy = syz = szz = 0.0
    for i in range(s, e + 1):
        dx = P[i, 0] - cx
        dy = P[i, 1] - cy
        dz = P[i, 2] - cz
        sxx += dx * dx
        sxy += dx * dy
        sxz += dx * dz
        syy += dy * dy
        syz += dy * dz
        szz += dz * dz
    M = np.empty((3, 3))
    M[0, 0] = sxx
    M[0, 1] = M[1, 0] = sxy
    M[0, 2] = M[2, 0] = sxz
    M[1, 1] = syy
    M[1, 2] = M[2, 1] = syz
    M[2, 2] = szz
    w, V = np.linalg.eigh(M)
    d = V[:, 2].copy()
    if (P[e, 0] - P[s, 0]) * d[0] + (P[e, 1] - P[s, 1]) * d[1] + (P[e, 2] - P[s, 2]) * d[2] < 0:
        d = -d
    c = np.empty(3)
    c[0] = cx
    c[1] = cy
    c[2] = cz
    return c, d


@kernel
def _within(P: np.ndarray, inv2: np.ndarray, s: int, e: int, c: np.ndarray, d: np.ndarray,
            lim2: float) -> bool:
    """Whether every point of P[s:e+1] lies within normalized distance sqrt(lim2) of line
    (c, d); ``inv2`` is 1 / sigma^2 per point (squares: no square root or division per
    point). Stops at the first point beyond."""
    for i in range(s, e + 1):
        vx = P[i, 0] - c[0]
        vy = P[i, 1] - c[1]
        vz = P[i, 2] - c[2]
        t = vx * d[0] + vy * d[1] + vz * d[2]
        rx = vx - t * d[0]
        ry = vy - t * d[1]
        rz = vz - t * d[2]
        if (rx * rx + ry * ry + rz * rz) * inv2[i] > lim2:
            return False
    return True


@kernel
def _split_merge(P: np.ndarray, S: np.ndarray, thr: np.ndarray, work: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split-and-merge of one scan line into segments.

    ``work[0]`` is increased by the samples visited (every split's chord distances, every
    merge's fit and residuals): the unit of ``Config.max_edge_work``.

    Returns (m, 2) inclusive bounds, (m, 6) the centroid and direction of each segment's
    line (:func:`_fit`) and (m,) whether that is set (a segment that a merge made; the
    others are not fitted here).

    ``thr[n]`` is the largest normalized residual allowed in a segment of n points. The
    residuals are compared squared, against ``thr**2`` (the same order and decisions, up
    to a rounding of the last bit, without a square root and a division per point).
    """
    n = P.shape[0]
    inv2 = np.empty(n)
    X = np.empty(n)
    Y = np.empty(n)
    Z = np.empty(n)
    z2 = np.empty(n)
    for i in range(n):
        inv2[i] = 1.0 / (S[i] * S[i])
        X[i], Y[i], Z[i] = P[i, 0], P[i, 1], P[i, 2]
    bounds = np.empty((n, 2), np.int64)
    nb_ = 0
    stack = np.empty((n + 1, 2), np.int64)
    sp = 0
    stack[0, 0] = 0
    stack[0, 1] = n - 1
    sp = 1
    # split: depth-first on the chord, emitting segments left to right
    out = np.empty((n, 2), np.int64)
    no = 0
    while sp > 0:
        sp -= 1
        s = stack[sp, 0]
        e = stack[sp, 1]
        if e - s < 2:
            out[no, 0] = s
            out[no, 1] = e
            no += 1
            continue
        ax, ay, az = P[s, 0], P[s, 1], P[s, 2]
        ux, uy, uz = P[e, 0] - ax, P[e, 1] - ay, P[e, 2] - az
        L = math.sqrt(ux * ux + uy * uy + uz * uz)
        best = 0.0
        arg = -1
        if L > 0:
            work[0] += e - s - 1
            ux /= L
            uy /= L
            uz /= L
            # two passes: the distances (element-wise over coordinate arrays, which the
            # compiler vectorizes), then the first largest
            for i in range(s + 1, e):
                vx, vy, vz = X[i] - ax, Y[i] - ay, Z[i] - az
                t = vx * ux + vy * uy + vz * uz
                rx, ry, rz = vx - t * ux, vy - t * uy, vz - t * uz
                z2[i] = (rx * rx + ry * ry + rz * rz) * inv2[i]
            for i in range(s + 1, e):
                if z2[i] > best:
                    best = z2[i]
                    arg = i
        if arg >= 0 and best > thr[e - s + 1] * thr[e - s + 1]:
            # push right first so the left half is processed first
            stack[sp, 0] = arg
            stack[sp, 1] = e
            sp += 1
            stack[sp, 0] = s
            stack[sp, 1] = arg
            sp += 1
        else:
            out[no, 0] = s
            out[no, 1] = e
            no += 1
    # make segments disjoint: a shared vertex goes to the side whose chord fits it better
    for k in range(no - 1):
        v = out[k, 1]
        if out[k + 1, 0] == v:
            out[k + 1, 0] = v + 1
    # merge neighbours whose union is still a line (TLS fit, max normalized residual); the
    # fit of a segment's last merge is its line (:func:`_fit` of its bounds), kept
    fits = np.empty((n, 6))
    fitted = np.zeros(n, np.bool_)
    k = 0
    while k < no:
        s = out[k, 0]
        e = out[k, 1]
        if e < s:
            k += 1
            continue
        if nb_ > 0:
            ps = bounds[nb_ - 1, 0]
            if e - ps + 1 >= 3:
                work[0] += 2 * (e - ps + 1)
                c, d = _fit(P, ps, e)
                if _within(P, inv2, ps, e, c, d, thr[e - ps + 1] * thr[e - ps + 1]):
                    bounds[nb_ - 1, 1] = e
                    fits[nb_ - 1, :3] = c
                    fits[nb_ - 1, 3:] = d
                    fitted[nb_ - 1] = True
                    k += 1
                    continue
        bounds[nb_, 0] = s
        bounds[nb_, 1] = e
        fitted[nb_] = False
        nb_ += 1
        k += 1
    return bounds[:nb_], fits[:nb_], fitted[:nb_]


@kernel
def _split_at_steps(P: np.ndarray, S: np.ndarray, thr: np.ndarray, work: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_split_merge` of each piece of the scan line between range steps.

    Split-and-merge measures residuals perpendicular to a line. A total least-squares
    "line" through a far step runs nearly along the rays (the step's depth outweighs its
    width), so its perpendicular residuals stay small and it bridges the jump: the top
    and the floor behind it one segment, and no edge between them. So no line may span a
    step, a change of level between successive samples:

    * their ranges differ by more than ``thr[n]`` (the split test's Bonferroni level over
      the line's n samples) times the sigma of the difference;
    * that increment also differs so from the increments next to it (a steep face's
      increments run on alike; a crease into one changes them once, and is left to
      split-and-merge; shredding such faces into pieces found fewer tops);
    * the surface does not resume at its level within :data:`STEP_RUN_MAX` samples
      (outliers, a correlated blob or a narrow groove stay split-and-merge's, as before).

    Returns as :func:`_split_merge`, over the whole line.
    """
    n = P.shape[0]
    cut = np.empty(n + 1, np.int64)
    cut[0] = 0
    nc = 1
    t2 = thr[n] * thr[n]
    R = np.empty(n)
    for i in range(n):
        R[i] = math.sqrt(P[i, 0] * P[i, 0] + P[i, 1] * P[i, 1] + P[i, 2] * P[i, 2])
    step = np.zeros(n + 1, np.bool_)  # step[i]: between samples i - 1 and i
    for i in range(1, n):
        dr = R[i] - R[i - 1]
        step[i] = dr * dr > t2 * (S[i - 1] * S[i - 1] + S[i] * S[i])
        # a change of level, not a steep face: the increment differs significantly from
        # its neighbours' too (a face's increments run on alike; a crease into a steep
        # face changes them once, and is split-and-merge's to find)
        for j in (i - 1, i + 1):
            if step[i] and 1 <= j < n:
                dd = dr - (R[j] - R[j - 1])
                q = min(i, j)  # the sample both increments share: twice in dd
                v = (S[i - 1] * S[i - 1] + S[i] * S[i] + S[j - 1] * S[j - 1]
                     + S[j] * S[j] + 2.0 * S[q] * S[q])
                if dd * dd <= t2 * v:
                    step[i] = False
    # a run of a few samples off a surface that resumes at its level after them (a heavy
    # tail's outliers, a correlated blob, a narrow groove) is no step: split-and-merge
    # sets it apart as before; the step test only keeps lines off a change of level
    for i in range(1, n):
        if not step[i]:
            continue
        for j in range(i + 1, min(n, i + STEP_RUN_MAX + 1)):
            if step[j]:
                dr = R[j] - R[i - 1]
                if dr * dr <= t2 * (S[i - 1] * S[i - 1] + S[j] * S[j]):
                    for k in range(i, j + 1):
                        step[k] = False
                    break
    for i in range(1, n):
        if step[i]:
            cut[nc] = i
            nc += 1
    cut[nc] = n
    if nc == 1:
        return _split_merge(P, S, thr, work)
    bounds = np.empty((n, 2), np.int64)
    fits = np.empty((n, 6))
    fitted = np.zeros(n, np.bool_)
    m = 0
    for k in range(nc):
        a, b = cut[k], cut[k + 1]
        if b - a < 3:  # too short to test: one segment (dropped later if below min_pts)
            bounds[m, 0] = a
            bounds[m, 1] = b - 1
            fitted[m] = False
            m += 1
            continue
        Bk, Fk, fk = _split_merge(P[a:b], S[a:b], thr, work)
        for j in range(Bk.shape[0]):
            bounds[m, 0] = Bk[j, 0] + a
            bounds[m, 1] = Bk[j, 1] + a
            fits[m] = Fk[j]
            fitted[m] = fk[j]
            m += 1
    return bounds[:m], fits[:m], fitted[:m]


@kernel
def _range_on_line(u: np.ndarray, c: np.ndarray, d: np.ndarray) -> float:
    """Range along unit ray u of the point of line (c, d) closest to the ray."""
    # minimize |s u - c - t d|^2 over s, t
    ud = np.dot(u, d)
    uc = np.dot(u, c)
    dc = np.dot(d, c)
    den = 1.0 - ud * ud
    if den < 1e-12:
        return np.nan
    return (uc - ud * dc) / den


@kernel
def _closest_between(c1, d1, c2, d2):
    """Midpoint of the common perpendicular of two lines."""
    w = c1 - c2
    a = np.dot(d1, d2)
    b1 = np.dot(d1, w)
    b2 = np.dot(d2, w)
    den = 1.0 - a * a
    if den < 1e-12:
        return 0.5 * (c1 + c2)
    t1 = (a * b2 - b1) / den
    t2 = (b2 - a * b1) / den
    return 0.5 * (c1 + t1 * d1 + c2 + t2 * d2)


@kernel
def _scan_line_edges(
    P: np.ndarray,
    S: np.ndarray,
    pix: np.ndarray,
    thr: np.ndarray,
    run_thr: np.ndarray,
    jump_crit: float,
    min_crease: float,
    z_crease: float,
    min_pts: int,
    rho: np.ndarray,
    out_pix: np.ndarray,
    out_pt: np.ndarray,
    out_along: np.ndarray,
    out_sig: np.ndarray,
    out_kind: np.ndarray,
    out_strength: np.ndarray,
    out_stat: np.ndarray,
    out_crit: np.ndarray,
    out_test: np.ndarray,
    n_out: int,
    work: np.ndarray,
) -> int:
    """Edge points of one scan line (valid samples only, in order).

    P (n, 3) points, S (n,) their noise sigma, pix (n,) their position in the image line,
    rho (K + 1,) the noise's correlation at 0..K pixels along the line (rho[0] = 1; one
    value: white noise). Appends to the out_* arrays from index n_out; returns the new
    count.
    """
    n = P.shape[0]
    if n < 2 * min_pts:
        return n_out
    B, fits, fitted = _split_at_steps(P, S, thr, work)
    m = B.shape[0]
    # keep segments with enough points
    keep = np.empty(m, np.int64)
    nk = 0
    for k in range(m):
        if B[k, 1] - B[k, 0] + 1 >= min_pts:
            keep[nk] = k
            nk += 1
    cs = np.empty((nk, 3))
    ds = np.empty((nk, 3))
    vd = np.empty(nk)
    tpos = np.empty(n)  # each sample's position along its segment's line, metres
    for j in range(nk):
        k = keep[j]
        if fitted[k]:  # the merge's fit of these very bounds
            c, d = fits[k, :3], fits[k, 3:]
        else:
            c, d = _fit(P, B[k, 0], B[k, 1])
        cs[j] = c
        ds[j] = d
        # direction variance of a line fit: mean sigma^2 / sum (t - t_mean)^2 for white
        # noise; for correlated noise sum_ij t_i t_j s_i s_j rho(|i - j|) / (sum t^2)^2
        # (a fold of a few pixels' wobble is no crease where the wobble spans them)
        st2 = 0.0
        ss = 0.0
        for i in range(B[k, 0], B[k, 1] + 1):
            t = (P[i, 0] - c[0]) * d[0] + (P[i, 1] - c[1]) * d[1] + (P[i, 2] - c[2]) * d[2]
            tpos[i] = t  # kept for the correlated sum below
            st2 += t * t
            ss += S[i] * S[i]
        vd[j] = ss / (B[k, 1] - B[k, 0] + 1) / max(st2, 1e-30)
        if rho.shape[0] > 1:
            K = rho.shape[0] - 1
            num = 0.0
            for i in range(B[k, 0], B[k, 1] + 1):
                ti = tpos[i]
                for q in range(i, B[k, 1] + 1):
                    lag = abs(pix[q] - pix[i])
                    if lag > K:
                        break
                    w = ti * tpos[q] * S[i] * S[q] * rho[lag]
                    num += w if q == i else 2.0 * w
            vd[j] = max(vd[j], num / max(st2 * st2, 1e-60))
    # grooves inside a segment: a short run of samples significantly behind its line, with
    # the samples around it back on the line (a seam narrower than the split test can see)
    for j in range(nk):
        k = keep[j]
        s0 = B[k, 0]
        s1 = B[k, 1]
        n_seg = s1 - s0 + 1
        if n_seg < 2 * GROOVE_CONTEXT + 2:
            continue
        t_run = run_thr[n_seg]
        z = np.empty(n_seg)
        cx, cy, cz = cs[j, 0], cs[j, 1], cs[j, 2]
        dx, dy, dz = ds[j, 0], ds[j, 1], ds[j, 2]
        dc = dx * cx + dy * cy + dz * cz
        for i in range(s0, s1 + 1):
            # the line's range along this sample's ray (as _range_on_line, in scalars)
            r = math.sqrt(P[i, 0] ** 2 + P[i, 1] ** 2 + P[i, 2] ** 2)
            ud = (P[i, 0] * dx + P[i, 1] * dy + P[i, 2] * dz) / r
            uc = (P[i, 0] * cx + P[i, 1] * cy + P[i, 2] * cz) / r
            den = 1.0 - ud * ud
            z[i - s0] = (r - (uc - ud * dc) / den) / S[i] if den > 1e-12 else 0.0
        i = GROOVE_CONTEXT
        while i < n_seg - GROOVE_CONTEXT:
            if z[i] <= t_run:
                i += 1
                continue
            e = i
            while e + 1 < n_seg and z[e + 1] > t_run:
                e += 1
            run = e - i + 1
            if run >= GROOVE_MIN_RUN and run <= GROOVE_MAX_RUN and e + GROOVE_CONTEXT < n_seg:
                ctx = 0.0
                for q in range(1, GROOVE_CONTEXT + 1):
                    ctx = max(ctx, z[i - q], z[e + q])
                kd = i
                for q in range(i, e + 1):
                    if z[q] > z[kd]:
                        kd = q
                # the deepest sample must pass the single-sample test too: runs alone are
                # evidence only for white noise, and real sensors' noise is correlated
                if ctx < t_run and z[kd] > thr[n_seg]:
                    ip = s0 + kd
                    u = P[ip] / math.sqrt(np.dot(P[ip], P[ip]))
                    rl = _range_on_line(u, cs[j], ds[j])
                    out_pt[n_out] = rl * u
                    out_along[n_out] = ds[j]
                    out_sig[n_out] = run * math.sqrt(np.dot(P[s0 + e] - P[s0 + i],
                                                            P[s0 + e] - P[s0 + i])) / max(
                        run - 1, 1) / math.sqrt(12.0)
                    out_pix[n_out] = pix[ip]
                    out_kind[n_out] = 4
                    out_strength[n_out] = z[kd] * S[ip]
                    out_stat[n_out] = z[kd]
                    out_crit[n_out] = t_run
                    out_test[n_out] = 1
                    n_out += 1
            i = e + 1
    for j in range(nk - 1):
        ka = keep[j]
        kb = keep[j + 1]
        ia = B[ka, 1]
        ib = B[kb, 0]
        ca = cs[j]
        da = ds[j]
        cb = cs[j + 1]
        db = ds[j + 1]
        ua = P[ia] / math.sqrt(np.dot(P[ia], P[ia]))
        ub = P[ib] / math.sqrt(np.dot(P[ib], P[ib]))
        # ranges of both lines on the two rays bounding the break
        ra_a = _range_on_line(ua, ca, da)
        rb_a = _range_on_line(ua, cb, db)
        ra_b = _range_on_line(ub, ca, da)
        rb_b = _range_on_line(ub, cb, db)
        dA = ra_a - rb_a
        dB = ra_b - rb_b
        sig2 = S[ia] * S[ia] + S[ib] * S[ib]
        J = 0.0
        if np.isfinite(dA) and np.isfinite(dB) and dA * dB > 0:
            J = min(abs(dA), abs(dB))
        elif not (np.isfinite(dA) and np.isfinite(dB)):
            J = float(abs(np.linalg.norm(P[ib] - P[ia])))
        tstat = J * J / sig2
        # a jump must also show in the measurements at the break, not only between the
        # extrapolated lines (a steep side seen at grazing incidence extrapolates badly)
        dm = math.sqrt(np.dot(P[ib], P[ib])) - math.sqrt(np.dot(P[ia], P[ia]))
        if dm * dm / sig2 <= jump_crit:
            tstat = min(tstat, dm * dm / sig2)
        cosang = abs(np.dot(da, db))
        if cosang > 1.0:
            cosang = 1.0
        ang = math.acos(cosang)
        if tstat > jump_crit:
            # jump: the edge belongs to the nearer surface
            near_a = (ra_a + ra_b) < (rb_a + rb_b) if np.isfinite(dA + dB) else (
                np.dot(P[ia], P[ia]) < np.dot(P[ib], P[ib])
            )
            if near_a:
                i_end = ia
                i_next = ia + 1
                c = ca
                d = da
            else:
                i_end = ib
                i_next = ib - 1
                c = cb
                d = db
            u1 = P[i_end] / math.sqrt(np.dot(P[i_end], P[i_end]))
            u2 = P[i_next] / math.sqrt(np.dot(P[i_next], P[i_next]))
            r1 = _range_on_line(u1, c, d)
            r2 = _range_on_line(u2, c, d)
            m1 = math.sqrt(np.dot(P[i_end], P[i_end]))
            # a line seen almost along the ray extrapolates wildly: stay with the measurement
            if not (np.isfinite(r1) and np.isfinite(r2)) or abs(r1 - m1) > 5.0 * S[i_end]:
                r1 = m1
                r2 = m1
            q1 = r1 * u1
            q2 = r2 * u2
            step = math.sqrt(np.dot(q2 - q1, q2 - q1))
            # samples between ia and ib in the image may be missing: one pixel step
            npx = abs(pix[i_next] - pix[i_end])
            if npx > 1:
                step = step / npx
            h = q2 - q1
            hn = math.sqrt(np.dot(h, h))
            dirv = h / hn if hn > 0 else d
            out_pt[n_out] = q1 + 0.5 * step * dirv
            out_along[n_out] = dirv
            out_sig[n_out] = step / math.sqrt(12.0)
            out_pix[n_out] = pix[i_end]
            out_kind[n_out] = 1
            out_strength[n_out] = J
            out_stat[n_out] = tstat
            out_crit[n_out] = jump_crit
            out_test[n_out] = 1
            n_out += 1
        elif (ang - min_crease) / math.sqrt(vd[j] + vd[j + 1]) > z_crease:
            q = _closest_between(ca, da, cb, db)
            rq = math.sqrt(np.dot(q, q))
            uq = q / rq
            # convex if the fold point is nearer than the chord through both segments' middles
            mid = 0.5 * (ca + cb)
            convex = np.dot(q, uq) < np.dot(mid, uq)
            # pixel: the sample (ia or ib) nearer to the fold
            ea = P[ia] - q
            eb = P[ib] - q
            ipx = pix[ia] if np.dot(ea, ea) <= np.dot(eb, eb) else pix[ib]
            out_pt[n_out] = q
            out_along[n_out] = da
            out_sig[n_out] = math.sqrt(sig2) / max(math.sin(ang), 0.05)
            out_pix[n_out] = ipx
            out_kind[n_out] = 2 if convex else 3
            out_strength[n_out] = ang
            out_stat[n_out] = (ang - min_crease) / math.sqrt(vd[j] + vd[j + 1])
            out_crit[n_out] = z_crease
            out_test[n_out] = 2
            n_out += 1
        elif ib - ia > 1:
            # collinear and continuous: a groove if the dropped samples lie behind both lines
            best = 0.0
            kbest = -1
            for i in range(ia + 1, ib):
                u = P[i] / math.sqrt(np.dot(P[i], P[i]))
                r = 0.5 * (_range_on_line(u, ca, da) + _range_on_line(u, cb, db))
                z = (math.sqrt(np.dot(P[i], P[i])) - r) / S[i]
                if np.isfinite(z) and z > best:
                    best = z
                    kbest = i
            if kbest >= 0 and best > thr[ib - ia]:
                u = P[kbest] / math.sqrt(np.dot(P[kbest], P[kbest]))
                r = 0.5 * (_range_on_line(u, ca, da) + _range_on_line(u, cb, db))
                mk = math.sqrt(np.dot(P[kbest], P[kbest]))
                if not np.isfinite(r) or abs(r - mk) > 0.5 * abs(mk):
                    continue
                q = r * u
                w = P[ib] - P[ia]
                out_pt[n_out] = q
                wn = math.sqrt(np.dot(w, w))
                out_along[n_out] = w / wn if wn > 0 else da
                out_sig[n_out] = wn / math.sqrt(12.0)
                out_pix[n_out] = pix[kbest]
                out_kind[n_out] = 4
                out_strength[n_out] = best * S[kbest]
                out_stat[n_out] = best * best
                out_crit[n_out] = thr[ib - ia] ** 2
                out_test[n_out] = 1
                n_out += 1
    return n_out


@kernel
def _all_lines(
    P: np.ndarray,
    S: np.ndarray,
    thr: np.ndarray,
    run_thr: np.ndarray,
    jump_crit: float,
    min_crease: float,
    z_crease: float,
    min_pts: int,
    axis: int,
    rho: np.ndarray,
    budget: int,
    work: np.ndarray,
):
    """Run the scan-line detector over every row (axis=0) or column (axis=1); ``rho`` is
    the noise's correlation along them at 0..K pixels.

    With ``budget`` > 0 no line is started once ``work[0]`` (samples the split-and-merge
    visited, :func:`_split_merge`) has reached it. The last return value is the number of
    lines run (all of them unless the budget stopped the axis)."""
    H, W = S.shape
    nlines = H if axis == 0 else W
    L = W if axis == 0 else H
    cap = H * W // 2 + 16
    out_pix = np.empty(cap, np.int64)
    out_line = np.empty(cap, np.int64)
    out_pt = np.empty((cap, 3))
    out_along = np.empty((cap, 3))
    out_sig = np.empty(cap)
    out_kind = np.empty(cap, np.uint8)
    out_strength = np.empty(cap)
    out_stat = np.empty(cap)
    out_crit = np.empty(cap)
    out_test = np.empty(cap, np.uint8)
    n_out = 0
    buf = np.empty((L, 3))
    sbuf = np.empty(L)
    pbuf = np.empty(L, np.int64)
    done = nlines
    for li in range(nlines):
        if budget > 0 and work[0] >= budget:
            done = li
            break
        nv = 0
        for k in range(L):
            if axis == 0:
                p = P[li, k]
                s = S[li, k]
            else:
                p = P[k, li]
                s = S[k, li]
            if np.isfinite(s):
                buf[nv] = p
                sbuf[nv] = s
                pbuf[nv] = k
                nv += 1
        if nv < 2 * min_pts:
            continue
        if n_out + L > cap:
            break
        n0 = n_out
        n_out = _scan_line_edges(
            buf[:nv], sbuf[:nv], pbuf[:nv], thr, run_thr, jump_crit, min_crease, z_crease,
            min_pts, rho,
            out_pix, out_pt, out_along, out_sig, out_kind, out_strength, out_stat,
            out_crit, out_test, n_out, work,
        )
        # a surface that runs into no return out to the image border ends there
        for end in range(2):
            if end == 0:
                a, b, run = 0, 1, pbuf[0]
            else:
                a, b, run = nv - 1, nv - 2, L - 1 - pbuf[nv - 1]
            if run < NO_RETURN_PX or n_out >= cap:
                continue
            h = buf[a] - buf[b]
            hn = math.sqrt(np.dot(h, h))
            if hn <= 0.0:
                continue
            step = hn / max(abs(pbuf[a] - pbuf[b]), 1)  # one pixel step, outward
            dirv = h / hn
            out_pt[n_out] = buf[a] + 0.5 * step * dirv
            out_along[n_out] = dirv
            out_sig[n_out] = step / math.sqrt(12.0)
            out_pix[n_out] = pbuf[a]
            out_kind[n_out] = 1
            out_strength[n_out] = np.inf
            out_stat[n_out] = run
            out_crit[n_out] = NO_RETURN_PX
            out_test[n_out] = 3
            n_out += 1
        for k in range(n0, n_out):
            out_line[k] = li
    return (
        out_pix[:n_out], out_line[:n_out], out_pt[:n_out], out_along[:n_out],
        out_sig[:n_out], out_kind[:n_out], out_strength[:n_out], out_stat[:n_out],
        out_crit[:n_out], out_test[:n_out], done,
    )


# --- public --------------------------------------------------------------------------------


def residual_thresholds(n_max: int, alpha: float) -> np.ndarray:
    """Largest normalized residual a line of n points may show: z_{1 - alpha / (2n)}.

    Bonferroni over the n residuals, so a true line is split with probability <= alpha.
    """
    n = np.arange(n_max + 2, dtype=np.float64)
    n[0] = 1
    return np.asarray(norm_isf(alpha / (2.0 * n)), dtype=np.float64)


def run_thresholds(n_max: int, alpha: float) -> np.ndarray:
    """Level t that GROOVE_MIN_RUN consecutive samples of an n-sample line all exceed on one
    side with probability alpha: n * Phi(-t)^k = alpha (Bonferroni over the positions)."""
    n = np.arange(n_max + 2, dtype=np.float64)
    n[0] = 1
    return np.asarray(norm_isf((alpha / n) ** (1.0 / GROOVE_MIN_RUN)), dtype=np.float64)


def correlation_lags(length_px: float) -> np.ndarray:
    """The noise's correlation at 0..K pixels, exp(-k / length) (``NoiseModel.corr_px_*``),
    out to where it falls below 0.01; ``[1.0]`` (white noise) for length 0."""
    if not length_px > 0:
        return np.ones(1)
    K = max(1, int(math.ceil(length_px * math.log(100.0))))
    return np.exp(-np.arange(K + 1) / length_px)


def _model_sigma(scan: Scan, config: Config) -> tuple[np.ndarray, np.ndarray]:
    """The ranges and the noise model's per-pixel sigma (range and lateral), (H, W) metres."""
    r = scan.range.astype(np.float64)
    sr = config.noise.sigma_range(r)
    sl = config.noise.sigma_lateral(r, scan.sensor.pixel_angle)
    return r, np.sqrt(sr * sr + sl * sl)


def noise_gain(scan: Scan, config: Config) -> np.ndarray:
    """The scan's local noise scale over the model's, (H, W) >= 1 (:func:`local_scale` of
    the model's sigma): what :func:`point_sigma` multiplies by, and what the seam tests
    divide residuals by (:class:`boxloc.stages.verify.VerifyContext`). The pipeline computes
    it once per scan and hands it to both."""
    return local_scale(*_model_sigma(scan, config))


def point_sigma(scan: Scan, config: Config, gain: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel noise sigma (metres) used for line fitting, (H, W), NaN where no return:
    the noise model's, times the scan's local scale (``gain``: :func:`noise_gain`, computed
    here when not given)."""
    r, S = _model_sigma(scan, config)
    return S * (local_scale(r, S) if gain is None else gain)


#: Side of the tiles over which the local noise scale is measured, pixels (as the noise
#: stage's flat tiles, :data:`boxloc.stages.scan_noise.PATCH_PX`).
SCALE_TILE_PX = 16


@kernel
def _tile_medians(A: np.ndarray, th: int, tw: int, tile: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Per tile (i, j) of ``tile`` x ``tile`` pixels of both planes of A (2, H, W), the
    number of its finite values and their median, (th, tw) each: ``nanmedian_last`` over
    the tile's values with the infinities made NaN, bit for bit for values without -0.0
    (a selection and a sort pick the same value; the two middle ones' mean as there)."""
    cnt = np.zeros((th, tw), np.int64)
    med = np.empty((th, tw))
    buf = np.empty(2 * tile * tile)
    for i in range(th):
        for j in range(tw):
            m = 0
            for p in range(2):
                for y in range(i * tile, (i + 1) * tile):
                    for x in range(j * tile, (j + 1) * tile):
                        v = A[p, y, x]
                        if math.isfinite(v):
                            buf[m] = v
                            m += 1
            cnt[i, j] = m
            if m == 0:
                med[i, j] = math.nan
                continue
            k = (m - 1) // 2
            lo = _select(buf, k, 0, m - 1)
            med[i, j] = lo if m % 2 == 1 else (lo + _least_after(buf, k, m)) / 2.0
    return cnt, med


def local_scale(r: np.ndarray, S: np.ndarray, tile: int = SCALE_TILE_PX) -> np.ndarray:
    """How much larger than its typical level the noise is around each pixel, (H, W) >= 1.

    Real depth noise is heavy-tailed because its scale varies over the image (the matching
    quality of a stereo camera, the returned power of a time-of-flight pixel): a sample
    beyond 5 sigma is an ordinary sample where the local scale is 3x. A test scaled by the
    range law alone then splits such regions into false edges. Per tile, the median
    |second difference| of the ranges along rows and columns over the model's sigma, over
    its median across the scan's tiles, is the local scale (a median: the few triplets
    that straddle an edge or a seam do not move it); tiles at or below the scan's level
    keep the model (so a white-noise scan's tests keep their rate, and the model, fitted
    to the scan's flat tiles, stays the scale at the typical level); bilinear between tile
    centres. Second differences rather than plane residuals: correlated noise partly
    cancels in them, but by the same factor in every tile, which the ratio removes.

    Parameters
    ----------
    r : (H, W) float64, metres (NaN or <= 0: no return)
    S : (H, W) float64, metres: the noise model's sigma
    tile : int, pixels
    """
    H, W = r.shape
    th, tw = H // tile, W // tile
    out = np.ones((H, W))
    if th < 1 or tw < 1:
        return out
    with np.errstate(invalid="ignore", divide="ignore"):
        zr = np.abs(r[:, :-2] - 2.0 * r[:, 1:-1] + r[:, 2:]) / S[:, 1:-1]
        zc = np.abs(r[:-2] - 2.0 * r[1:-1] + r[2:]) / S[1:-1]
    A = np.full((2, H, W), np.nan)
    A[0, :, 1:-1] = zr
    A[1, 1:-1, :] = zc
    # per tile, its finite values' count and median (NaN for a tile without returns)
    n, med = _tile_medians(A, th, tw, tile)
    good = (n >= tile * tile // 2) & np.isfinite(med) & (med > 0)
    if good.sum() < 4:
        return out
    g = np.where(good, med / np.median(med[good]), 1.0)
    g = np.maximum(g, 1.0).astype(np.float32)
    full = cv2.resize(g, (tw * tile, th * tile), interpolation=cv2.INTER_LINEAR)
    out[:th * tile, :tw * tile] = full
    # the border strips beyond the last whole tile take the nearest tile's value
    if th * tile < H:
        out[th * tile:, :] = out[th * tile - 1:th * tile, :]
    if tw * tile < W:
        out[:, tw * tile:] = out[:, tw * tile - 1:tw * tile]
    return out


#: A scan line finds an edge reliably when it crosses it within this angle of the edge's
#: normal; beyond it (a row running along a near-horizontal edge) the breakpoint position is
#: ill-defined, and the other scan direction, which crosses the edge better, is used.
MAX_CROSSING_ANGLE = math.radians(60.0)


def _crossing_ok(r: np.ndarray, c: np.ndarray, scan_dir: np.ndarray,
                 shape: tuple[int, int]) -> np.ndarray:
    """Detections whose scan line crosses the local edge within MAX_CROSSING_ANGLE, (n,) bool.

    The edge's local orientation is that of the structure tensor of the edge-pixel map.
    """
    if len(r) == 0:
        return np.zeros(0, bool)
    E: np.ndarray = np.zeros(shape, np.float32)
    E[r, c] = 1.0
    E = cv2.GaussianBlur(E, (0, 0), 1.0)
    gx = cv2.Sobel(E, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(E, cv2.CV_32F, 0, 1, ksize=3)
    jxx = cv2.GaussianBlur(gx * gx, (0, 0), 2.0)[r, c]
    jyy = cv2.GaussianBlur(gy * gy, (0, 0), 2.0)[r, c]
    jxy = cv2.GaussianBlur(gx * gy, (0, 0), 2.0)[r, c]
    # dominant gradient direction of the edge map = across the edge
    theta = 0.5 * np.arctan2(2 * jxy, jxx - jyy)
    across_x = np.abs(np.cos(theta))  # |cos| of the angle between x and the edge normal
    across_y = np.abs(np.sin(theta))
    lim = math.cos(MAX_CROSSING_ANGLE)
    row = scan_dir == 1
    flat = (jxx + jyy) < 1e-12  # isolated points: no orientation, keep
    return flat | np.where(row, across_x >= lim, across_y >= lim)


def _fuse(flat: np.ndarray, pt: np.ndarray, cov: np.ndarray, kd: np.ndarray,
          stg: np.ndarray, sd: np.ndarray, chi3: float
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The detections of each pixel fused into one edge point by information weighting.

    A pixel's detections (its row's and its column's) are taken in kind order; those that
    agree with the first (chi2(3) on their difference, at ``chi3``) are fused: the
    information-weighted mean and covariance, the lowest kind (JUMP < CREASE_CONVEX <
    CREASE_CONCAVE < GROOVE), the largest strength and every scan direction. A pixel with
    one agreeing detection keeps the first as it is.

    The pixels' groups are computed together (batched LAPACK calls and reductions, by
    group size), each matrix and sum exactly as a loop over the pixels would: the same
    routines on the same operands, in the same order.

    Parameters
    ----------
    flat : (n,) int64, each detection's pixel (row x W + column)
    pt : (n, 3) float64, metres; cov : (n, 3, 3) float64, m^2
    kd, stg, sd : (n,) kinds (uint8), strengths, scan directions (uint8 bits)
    chi3 : float, the chi2(3) critical value at alpha

    Returns
    -------
    uniq : (m,) the pixels, ascending; then per pixel the point (m, 3), covariance
    (m, 3, 3), kind, strength and scan directions.
    """
    order = np.lexsort((kd, flat))
    uniq, start = np.unique(flat[order], return_index=True)
    stop = np.r_[start[1:], len(order)].astype(np.int64)
    n = len(uniq)
    idx1 = order[start]
    out_pt, out_cov = pt[idx1], cov[idx1]
    out_kind, out_str, out_dir = kd[idx1], stg[idx1], sd[idx1]
    size = stop - start
    multi = np.flatnonzero(size > 1)
    if not n or not multi.size:
        return uniq, out_pt, out_cov, out_kind, out_str, out_dir
    # every later detection of a pixel against its first: agree within chi2(3)?
    n_later = size[multi] - 1
    grp = np.repeat(multi, n_later)  # the pixel of each later detection
    # its place in its pixel's run of detections: 1 .. size - 1
    rank = np.arange(len(grp)) - np.repeat(np.cumsum(n_later) - n_later, n_later) + 1
    later, first = order[start[grp] + rank], idx1[grp]
    d = pt[later] - pt[first]
    x = np.linalg.solve(cov[later] + cov[first], d[..., None])
    agree = (d[:, None, :] @ x)[:, 0, 0] <= chi3
    later, grp = later[agree], grp[agree]
    # the fused groups: the first, then the agreeing ones in kind order, by group size
    k_of = np.bincount(grp, minlength=n) + 1
    for k in np.unique(k_of[grp]):
        gis = np.flatnonzero(k_of == k)
        members = np.empty((len(gis), k), np.int64)
        members[:, 0] = idx1[gis]
        members[:, 1:] = later[np.isin(grp, gis)].reshape(len(gis), k - 1)
        info = np.linalg.inv(cov[members])
        Cf = np.linalg.inv(info.sum(1))
        out_cov[gis] = 0.5 * (Cf + Cf.transpose(0, 2, 1))
        out_pt[gis] = (Cf @ np.einsum("gkij,gkj->gi", info, pt[members])[..., None])[..., 0]
        out_kind[gis] = kd[members].min(1)
        out_str[gis] = stg[members].max(1)
        out_dir[gis] = np.bitwise_or.reduce(sd[members], axis=1)
    return uniq, out_pt, out_cov, out_kind, out_str, out_dir


def detect_edges(scan: Scan, *, config: Config, gain: np.ndarray | None = None) -> EdgeMap:
    """Jump, crease and groove edges of a range image by scan-line approximation.

    Parameters
    ----------
    scan : Scan
        Range image and sensor model.
    config : Config
        Uses ``alpha``, ``noise`` and ``min_crease_angle``.
    gain : (H, W) float64, optional
        :func:`noise_gain` of the scan and config, if already computed (the pipeline's).

    Returns
    -------
    EdgeMap
        Edge labels per pixel and the sub-pixel edge points with covariances.

    References
    ----------
    X. Jiang, H. Bunke, "Edge detection in range images based on scan line approximation",
    CVIU 73(2), 1999. Katsoulas et al., ICRA 2002 ("edge map creation via scan line
    approximation").
    """
    H, W = scan.shape
    P = scan.points.astype(np.float64)
    S = point_sigma(scan, config, gain)
    thr = residual_thresholds(max(H, W), config.alpha)
    run_thr = run_thresholds(max(H, W), config.alpha)
    jump_crit = chi2_critical(1.0, config.alpha)
    # a crease is a fold significantly larger than min_crease_angle (one-sided z at alpha)
    z_crease = float(norm_isf(config.alpha))
    parts = []
    # the budget: half for the rows; the columns get the rest (what the rows left too)
    budget = config.max_edge_work
    work = np.zeros(1, np.int64)
    stopped = False
    for axis in (0, 1):
        share = 0 if not budget else (budget + 1) // 2 if axis == 0 else budget
        *part, done = _all_lines(
            P, S, thr, run_thr, jump_crit, config.min_crease_angle, z_crease,
            MIN_SEGMENT_POINTS, axis,
            correlation_lags(config.noise.corr_px_rows if axis == 0
                             else config.noise.corr_px_cols), share, work)
        stopped |= done < (H if axis == 0 else W)
        parts.append(part)
    rows, cols = [], []
    pts, along, sig, kinds, strength, stat, crit, test, sdir = [], [], [], [], [], [], [], [], []
    for axis, (pix, line, pt, al, sg, kd, stg, sta, cr, te) in enumerate(parts):
        if axis == 0:
            rows.append(line)
            cols.append(pix)
        else:
            rows.append(pix)
            cols.append(line)
        pts.append(pt)
        along.append(al)
        sig.append(sg)
        kinds.append(kd)
        strength.append(stg)
        stat.append(sta)
        crit.append(cr)
        test.append(te)
        sdir.append(np.full(pix.shape[0], 1 << axis, np.uint8))
    r = np.concatenate(rows).astype(np.int64)
    c = np.concatenate(cols).astype(np.int64)
    pt = np.concatenate(pts)
    al = np.concatenate(along)
    sg = np.concatenate(sig)
    kd = np.concatenate(kinds)
    stg = np.concatenate(strength)
    sta = np.concatenate(stat)
    cr = np.concatenate(crit)
    te = np.concatenate(test)
    sd = np.concatenate(sdir)

    cov = config.noise.covariance(pt, scan.sensor.pixel_angle)
    if config.noise.edge_px > 0:
        # the sensor's own edge blur, in pixel footprints along the scan line on the surface
        step = config.noise.pixel_footprint(pt, al, scan.sensor.pixel_angle)
        sg = np.sqrt(sg**2 + (config.noise.edge_px * step) ** 2)
    cov += (sg**2)[:, None, None] * (al[:, :, None] * al[:, None, :])

    # the tests at every breakpoint, in detection order
    is_jump_test = te == 1
    # test codes of the scan-line kernel: 1 jump (and groove), 2 crease, 3 no return
    kind_col = np.select([is_jump_test, te == 3], [int(TestKind.JUMP), int(TestKind.NO_RETURN)],
                         int(TestKind.CREASE)).astype(np.uint8)
    pval = float32_precision(np.where(is_jump_test, chi2_sf(sta, 1.0), np.nan))
    tests = TestTable(
        kind=kind_col, a=np.arange(len(r), dtype=np.int32), b=(r * W + c).astype(np.int32),
        statistic=sta, dof=np.where(is_jump_test, 1.0, 0.0).astype(np.float32), critical=cr,
        p_value=pval, accepted=np.ones(len(r), bool), alpha=config.alpha,
    )
    # the work of every scan line run; recorded (a BUDGET row) only where it stopped them
    tests = TestTable.concat([tests, TestTable.budget(BUDGET_EDGES, int(work[0]), budget,
                                                      stopped, config.alpha)], config.alpha)

    # keep each detection only from a scan line that crosses its edge at a fair angle
    keep = _crossing_ok(r, c, sd, (H, W))
    r, c, pt, al, sg, kd, stg, sta, cr, te, sd = (
        a[keep] for a in (r, c, pt, al, sg, kd, stg, sta, cr, te, sd)
    )
    cov = cov[keep]

    # fuse detections at the same pixel (row and column scans) by information weighting
    uniq, out_pt, out_cov, out_kind, out_str, out_dir = _fuse(
        r * W + c, pt, cov, kd, stg, sd, chi2_critical(3.0, config.alpha))
    n = len(uniq)
    labels = np.zeros((H, W), np.uint8)
    pix = np.stack(np.divmod(uniq, W), -1).astype(np.int32) if n else np.zeros((0, 2), np.int32)
    labels.reshape(-1)[uniq] = out_kind
    return EdgeMap(
        labels=labels,
        pixels=pix,
        # float32 precision, as the range they come from (0.2 um at 2-4 m); the covariances
        # keep 7 digits, far beyond the noise model's own accuracy. Half the log's bytes.
        points=float32_precision(out_pt),
        covariances=float32_precision(out_cov),
        kinds=out_kind,
        strength=float32_precision(out_str),
        scan_dir=out_dir,
        tests=tests,
    )


__all__ = ["detect_edges", "residual_thresholds", "point_sigma", "noise_gain", "EdgeKind"]

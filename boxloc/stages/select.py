"""Stage 7: minimum description length selection (paper Fig. 2, line 9; its ref [5]).

Recover-and-select after Leonardis, Gupta & Bajcsy (1995) and Jaklič, Leonardis & Solina
(2000, p. 122): choose the subset m of verified hypotheses maximizing ``m^T Q m`` with

    q_ii = K1 n_i - K2 xi_i - K3 N_i
    q_ij = (-2 K1 |R_i ∩ R_j| + K2 xi_ij) / 2

n_i the range points hypothesis i explains (its verification inliers), xi_i their summed
squared normalized residuals, N_i = 8 parameters of a rectangle, |R_i ∩ R_j| the points
both explain and xi_ij the larger of the two models' errors on them. Hypotheses of the
same face from different vertices overlap almost fully, so one survives: the one that
explains most points best. The search is greedy (add the best gain while it is positive).

Two deviations from Leonardis:

* The shared points of q_ij are subtracted from *both* models (factor 2). With tens of
  thousands of points per face, two rectangles of the same face a pixel apart would
  otherwise both be kept (the sliver one explains beyond the other outweighs the cost of a
  model); box faces are disjoint in space, so a point claimed twice is evidence against
  the pair, not for it.
* A model's cost is counted in *faces*, not pixels (``Config.mdl_face_points``).
  Leonardis' K3 N_i is a fixed number of points, but the points a box face shows grow
  with the square of the resolution and fall with the square of the distance: with raw
  counts a 320x240 camera 3.5 m away sees a 0.15 m face as ~130 points, which gain less
  than the 80 a model costs at the default weights (K1 n - K2 xi ~ 0.55 n), and no such
  face could ever be selected, while at 1280x960 and 1 m the same cost is nothing. So
  the cost is K3 N_i u_i / F, with u_i the points a face of the smallest box
  (``min_edge`` square) has at the candidate's place (its rasterized pixels over its
  area, times ``min_edge``^2) and F = ``mdl_face_points``: a parameter costs K3 / F of a
  smallest face wherever it is seen. Every other term already counts points, so
  sampling a scene s times more densely multiplies the whole of Q by s, and the greedy
  search chooses the same; the duplicates of one face still compete on their points.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse

from boxloc.config import Config
from boxloc.products import HypothesisSet, Selection, SelectReason, Verification

#: Parameters of a 3D rectangle: 6 of pose and 2 of size (paper §2).
RECTANGLE_PARAMETERS = 8


def overlap_counts(verification: Verification, attempts: np.ndarray) -> np.ndarray:
    """|R_i ∩ R_j|: inlier pixels shared by each pair of attempts, (c, c) int64."""
    c = len(attempts)
    if c == 0:
        return np.zeros((0, 0), np.int64)
    rows, cols = [], []
    for k, j in enumerate(attempts):
        px = verification.inliers_of(int(j))
        rows.append(np.full(len(px), k))
        cols.append(px)
    r = np.concatenate(rows)
    col = np.concatenate(cols).astype(np.int64)
    M = sparse.csr_array((np.ones(len(r), np.int64), (r, col)),
                          shape=(c, int(col.max()) + 1 if len(col) else 1))
    return (M @ M.T).toarray().astype(np.int64)


def face_units(verification: Verification, hypotheses: HypothesisSet, attempts: np.ndarray,
               min_edge: float) -> np.ndarray:
    """Points a face of the smallest box has at each attempt's place, (c,) float64.

    The attempt's rasterized pixels (``n_inside``, returns or not: dropouts do not thin
    the sampling) over its area, m^2, times ``min_edge``^2. NaN for an attempt with no
    pixel or no area.

    Parameters
    ----------
    verification : Verification
    hypotheses : HypothesisSet
        For the attempts' width and length, metres.
    attempts : (c,) int
        Attempt ids (rows of ``verification``).
    min_edge : float
        The shortest box edge, metres.
    """
    a = np.asarray(attempts, np.int64)
    att = verification.attempt[a].astype(np.int64)
    area = hypotheses.att_width[att] * hypotheses.att_length[att]
    px = verification.n_inside[a].astype(np.float64)
    ok = (area > 0) & (px > 0) & np.isfinite(area)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(ok, px / np.where(ok, area, 1.0) * min_edge**2, np.nan)


def select(verification: Verification, hypotheses: HypothesisSet, *, config: Config
           ) -> Selection:
    """Select the hypotheses that describe the scene best (MDL, greedy).

    Parameters
    ----------
    verification : Verification
        The verified attempts are the candidates.
    hypotheses : HypothesisSet
        The attempts' dimensions, for the points a face has at their place
        (:func:`face_units`).
    config : Config
        Uses ``mdl_k1``, ``mdl_k2``, ``mdl_k3``, ``mdl_face_points`` and ``min_edge``.

    Returns
    -------
    Selection
    """
    k1, k2, k3 = config.mdl_k1, config.mdl_k2, config.mdl_k3
    face_points = float(config.mdl_face_points)
    cand = np.flatnonzero(verification.accepted).astype(np.int32)
    c = len(cand)
    n_pts = verification.n_inliers[cand].astype(np.int64)
    err = verification.error[cand].astype(np.float64)
    n_par = np.full(c, RECTANGLE_PARAMETERS, np.int32)
    inter = overlap_counts(verification, cand)
    per_pt = err / np.maximum(n_pts, 1)
    unit = np.full(c, np.nan)
    cost = np.ones(c)  # K3 N is paid in points times this: a smallest face's points here / F
    if face_points > 0 and c:
        unit = face_units(verification, hypotheses, cand, config.min_edge)
        # a candidate without pixels or area (not one verification accepts) pays raw points
        cost = np.where(np.isfinite(unit) & (unit > 0), unit / face_points, 1.0)
    Q = np.zeros((c, c))
    if c:
        xi_ij = inter * np.maximum(per_pt[:, None], per_pt[None, :])
        Q = 0.5 * (-2.0 * k1 * inter + k2 * xi_ij)
        np.fill_diagonal(Q, k1 * n_pts - k2 * err - k3 * n_par * cost)
    chosen = np.zeros(c, bool)
    order: list[int] = []
    gain = np.diag(Q).copy() if c else np.zeros(0)
    while c:
        # marginal gain of adding k: q_kk + 2 sum_{j chosen} q_kj
        cand_gain = np.where(chosen, -np.inf, gain)
        k = int(np.argmax(cand_gain))
        if not np.isfinite(cand_gain[k]) or cand_gain[k] <= 0:
            break
        chosen[k] = True
        order.append(k)
        gain = gain + 2 * Q[:, k]
    objective = float(chosen @ Q @ chosen) if c else 0.0
    beaten = np.full(c, -1, np.int32)
    reason = np.zeros(c, np.uint8)
    for k in range(c):
        if chosen[k]:
            reason[k] = SelectReason.CHOSEN
            continue
        ov = np.where(chosen, inter[k], -1)
        if ov.size and ov.max() > 0:
            beaten[k] = int(np.argmax(ov))
        reason[k] = SelectReason.NO_GAIN if Q[k, k] <= 0 else SelectReason.OVERLAPS_CHOSEN
    return Selection(
        candidates=cand,
        hypothesis=verification.hypothesis[cand].astype(np.int32),
        n_points=n_pts.astype(np.int32),
        error=err,
        n_params=n_par,
        Q=Q,
        chosen=chosen,
        order=np.array(order, np.int32),
        objective=objective,
        beaten_by=beaten,
        reason=reason,
        k1=float(k1),
        k2=float(k2),
        k3=float(k3),
        unit=unit,
        face_points=face_points,
    )

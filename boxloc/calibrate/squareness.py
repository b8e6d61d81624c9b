"""How square a sensor sees square corners: an estimate of the prior ``angle_tolerance``.

The orthogonality test of the vertex stage (:func:`boxloc.stages.vertices.find_vertices`) compares
the cosine between two lines with its propagated variance plus ``angle_tolerance``², the
part of the departure from 90 degrees that the range-noise model does not explain: boxes
that are not quite square, and sensors that distort shapes. Structured-light depth
cameras are an example of the latter: on the mOSD Kinect frames the receding sides of box
tops come out sheared by several degrees, far beyond their propagated error, and with the
default (1 degree) no vertex forms on those tops.

:func:`estimate_angle_tolerance` measures it from scans of boxes: every pair of 3D lines
that meet near their ends (the meet and at-segment-ends tests at alpha, orthogonality not
asked) and lie within 45 degrees of square contributes its departure delta from 90
degrees. Square corners give |N(0, sigma)|, other pairs a broad background, so sigma is
estimated robustly (the half-normal median, delta_median / 0.6745) on the pairs within
the two-sided critical value at alpha, iterated to a fixed point. What the lines' own
propagated direction error explains is subtracted:
``angle_tolerance = sqrt(max(sigma^2 - median(var_prop), 0))``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from boxloc.config import Config
from boxloc.scan import Scan
from boxloc.stages.edges import detect_edges
from boxloc.stages.lines import find_lines
from boxloc.stages.vertices import find_vertices
from boxloc.stats import TestKind, half_normal_sigma

#: Pairs farther than this from square are not corners (collinear pieces, diagonals).
MAX_DEPARTURE = math.radians(45.0)


def corner_departures(scan: Scan, config: Config) -> tuple[np.ndarray, np.ndarray]:
    """Departures from 90 degrees of the line pairs of one scan that meet near their ends.

    Parameters
    ----------
    scan : Scan
    config : Config
        The noise model and priors of the edge, line and vertex stages.

    Returns
    -------
    delta : (k,) float64, radians
        ``arcsin(|b1 . b2|)`` of each pair that passes the meet and at-segment-ends tests,
        within :data:`MAX_DEPARTURE` of square.
    var_prop : (k,) float64, radians squared
        The propagated variance of the pair's cosine (the orthogonality test's variance
        without the tolerance).
    """
    # the config's draw of the trials, as the pipeline and edgeblur.edge_offsets draw them
    rng = np.random.default_rng(config.seed_for(scan.seed))
    edges = detect_edges(scan, config=config)
    lines = find_lines(scan, edges, config=config, rng=rng)
    T = find_vertices(lines, config=config).tests
    if len(lines) < 2 or len(T) == 0:
        return np.zeros(0), np.zeros(0)
    meet = (T.kind == TestKind.LINES_MEET) & T.accepted
    ends = (T.kind == TestKind.AT_SEGMENT_ENDS) & T.accepted
    pairs = sorted(set(zip(T.a[meet].tolist(), T.b[meet].tolist()))
                   & set(zip(T.a[ends].tolist(), T.b[ends].tolist())))
    if not pairs:
        return np.zeros(0), np.zeros(0)
    ia, ib = np.array(pairs, np.int64).T
    b1, b2 = lines.directions[ia], lines.directions[ib]
    cos = np.abs(np.einsum("ij,ij->i", b1, b2))
    S1, S2 = lines.covariances[ia][:, 3:, 3:], lines.covariances[ib][:, 3:, 3:]
    var = np.einsum("ni,nij,nj->n", b2, S1, b2) + np.einsum("ni,nij,nj->n", b1, S2, b1)
    delta = np.arcsin(np.clip(cos, 0.0, 1.0))
    keep = delta <= MAX_DEPARTURE
    return delta[keep], var[keep]


def estimate_angle_tolerance(
    scans: Sequence[Scan], config: Config, *, max_iter: int = 50,
) -> tuple[float, dict[str, Any]]:
    """Estimate ``angle_tolerance`` (radians) from scans of boxes.

    Parameters
    ----------
    scans : sequence of Scan
        Scans that show box corners (the more, the better; tens of corners at least).
    config : Config
        Its noise model should already be the sensor's (``boxloc calibrate-noise``).
    max_iter : int
        Bound on the robust fixed-point iteration.

    Returns
    -------
    tolerance : float
        Radians; 0 when the propagated error explains the spread.
    report : dict
        ``n_scans``, ``n_pairs``, ``n_corners`` (pairs kept), ``sigma_deg`` (spread of the
        departures), ``propagated_deg`` (median propagated sigma), ``tolerance_deg``,
        ``critical`` (the two-sided z at alpha), ``per_scan`` (pairs per scan).

    Raises
    ------
    InputError
        Fewer than 5 corner candidates in all the scans.
    """
    from boxloc.errors import InputError

    ds, vs, per = [], [], []
    for s in scans:
        d, v = corner_departures(s, config)
        ds.append(d)
        vs.append(v)
        per.append(int(len(d)))
    delta = np.concatenate(ds) if ds else np.zeros(0)
    var = np.concatenate(vs) if vs else np.zeros(0)
    if len(delta) < 5:
        raise InputError(f"too few line pairs meeting at corners to estimate angle_tolerance "
                         f"({len(delta)} in {len(scans)} scan(s)); scan more boxes")
    sigma, kept, k = half_normal_sigma(delta, config.alpha, max_iter)
    prop = float(np.median(var[kept]))
    tol = math.sqrt(max(sigma**2 - prop, 0.0))
    report = {
        "n_scans": len(scans), "n_pairs": int(len(delta)), "n_corners": int(kept.sum()),
        "sigma_deg": math.degrees(sigma), "propagated_deg": math.degrees(math.sqrt(prop)),
        "tolerance_deg": math.degrees(tol), "critical": k, "per_scan": per,
    }
    return tol, report


__all__ = ["corner_departures", "estimate_angle_tolerance", "MAX_DEPARTURE"]

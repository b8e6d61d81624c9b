"""How far a sensor blurs its depth edges: an estimate of the noise parameter ``edge_px``.

An edge point's covariance (:func:`boxloc.stages.edges.detect_edges`) holds the range noise and
the localization along its scan line that the scan-line fit explains (a jump's half sample,
a crease's intersection error). Structured-light cameras add their own blur: a depth edge is
found within a correlation window, so it wanders across its true place by about a pixel.
On a box top seen at grazing incidence one pixel is several millimetres, and edge points
that scatter that far smear the 1-D accumulators of :func:`boxloc.stages.hypotheses.
dimensions_from_edges` until the far sides have no peak. ``NoiseModel.edge_px`` adds that
blur, in pixels along the scan line, to every edge point's covariance.

:func:`estimate_edge_px` measures it from scans with straight edges (boxes), with no labels:
the edge and line stages run with the config's noise model; for every line with enough
support, the edge points of its kind along its extent give their distance from the line in
units of the pixel's footprint on the surface in that direction. Points on the line give
a half-normal distance, other edges a broad background, so the spread is estimated robustly
(:func:`boxloc.stats.half_normal_sigma`, as :mod:`boxloc.calibrate.squareness` does for angles);
what the points' own covariance already explains is subtracted:
``edge_px = sqrt(max(spread^2 - median(modelled)^2, 0))``.

On the simulator, whose edges have no sensor blur, the estimate is about 0.35 px (the
line fits' own error and the mixed pixels at jumps): values that small are within what
the model already covers, and the default is 0.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from boxloc.config import Config
from boxloc.scan import Scan
from boxloc.stages.edges import detect_edges
from boxloc.stages.lines import find_lines
from boxloc.stats import half_normal_sigma

#: Lines with fewer support points say little about the scatter around them.
MIN_SUPPORT = 20
#: Edge points farther than this (pixels) from a line are other structure, not its scatter.
CORRIDOR_PX = 4.0


def edge_offsets(scan: Scan, config: Config) -> tuple[np.ndarray, np.ndarray]:
    """Distances of edge points from the lines they lie along, in pixels, for one scan.

    Parameters
    ----------
    scan : Scan
    config : Config
        The noise model and priors of the edge and line stages.

    Returns
    -------
    offset : (k,) float64, pixels
        Each edge point's distance from a line of its kind with at least
        :data:`MIN_SUPPORT` points, within the line's extent and :data:`CORRIDOR_PX`,
        over the footprint of one pixel on the surface in the offset's direction.
    modelled : (k,) float64, pixels
        The standard deviation the point's covariance gives in that direction, same unit.
    """
    edges = detect_edges(scan, config=config)
    lines = find_lines(scan, edges, config=config,
                       rng=np.random.default_rng(config.seed_for(scan.seed)))
    if len(edges) == 0 or len(lines) == 0:
        return np.zeros(0), np.zeros(0)
    tree = cKDTree(edges.points)
    pixel_angle = scan.sensor.pixel_angle
    offs, mods = [], []
    for i in np.flatnonzero(lines.n_support >= MIN_SUPPORT):
        c, d = lines.points[i], lines.directions[i]
        t0, t1 = sorted(((lines.starts[i] - c) @ d, (lines.ends[i] - c) @ d))
        mid = c + 0.5 * (t0 + t1) * d
        # the corridor at its widest: CORRIDOR_PX footprints at the far end, at min_cos
        half = 0.5 * (t1 - t0)
        reach = CORRIDOR_PX * (np.linalg.norm(mid) + half) * pixel_angle / config.noise.min_cos
        nb = np.asarray(tree.query_ball_point(mid, half + reach), np.int64)
        nb = nb[edges.kinds[nb] == lines.kinds[i]]
        X = edges.points[nb] - c
        t = X @ d
        inside = (t > t0) & (t < t1)
        nb, X, t = nb[inside], X[inside], t[inside]
        e = X - t[:, None] * d
        dist = np.linalg.norm(e, axis=1)
        m = e / np.maximum(dist, 1e-12)[:, None]
        foot = config.noise.pixel_footprint(edges.points[nb], m, pixel_angle)
        off = dist / foot
        mod = np.sqrt(np.einsum("ni,nij,nj->n", m, edges.covariances[nb], m)) / foot
        keep = off < CORRIDOR_PX
        offs.append(off[keep])
        mods.append(mod[keep])
    if not offs:
        return np.zeros(0), np.zeros(0)
    return np.concatenate(offs), np.concatenate(mods)


def estimate_edge_px(
    scans: Sequence[Scan], config: Config, *, max_iter: int = 50,
) -> tuple[float, dict[str, Any]]:
    """Estimate ``noise.edge_px`` (pixels) from scans with straight depth edges.

    Parameters
    ----------
    scans : sequence of Scan
        Scans of boxes (or any straight edges); hundreds of edge points at least.
    config : Config
        Its range-noise model should already be the sensor's (``boxloc calibrate-noise``);
        its ``edge_px`` is set to 0 for the measurement.
    max_iter : int
        Bound on the robust fixed-point iteration.

    Returns
    -------
    edge_px : float
        Pixels; 0 when the modelled covariance explains the scatter.
    report : dict
        ``n_scans``, ``n_points`` (offsets measured), ``n_kept`` (within the critical value),
        ``spread_px``, ``modelled_px`` (median), ``edge_px``, ``critical``.

    Raises
    ------
    InputError
        Fewer than 100 edge points along lines in all the scans.
    """
    from boxloc.errors import InputError

    cfg = dataclasses.replace(config, noise=dataclasses.replace(config.noise, edge_px=0.0))
    parts = [edge_offsets(s, cfg) for s in scans]
    off = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0)
    mod = np.concatenate([p[1] for p in parts]) if parts else np.zeros(0)
    if len(off) < 100:
        raise InputError(f"too few edge points along lines to estimate edge_px ({len(off)} "
                         f"in {len(scans)} scan(s)); scan boxes with straight edges")
    sigma, kept, k = half_normal_sigma(off, config.alpha, max_iter)
    modelled = float(np.median(mod[kept]))
    edge_px = math.sqrt(max(sigma**2 - modelled**2, 0.0))
    report = {"n_scans": len(scans), "n_points": int(len(off)), "n_kept": int(kept.sum()),
              "spread_px": sigma, "modelled_px": modelled, "edge_px": edge_px,
              "critical": k}
    return edge_px, report


__all__ = ["edge_offsets", "estimate_edge_px", "MIN_SUPPORT", "CORRIDOR_PX"]

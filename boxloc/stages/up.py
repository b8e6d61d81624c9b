"""Which way is up, in the sensor frame.

With the sensor pose known, up is the base frame's z axis. Without it, up is the normal of
the dominant plane of the scan, turned toward the sensor: in a depalletizing scene the
largest planar area is the support (floor, pallet, table) or a layer of box tops, and all of
them are horizontal. The tilt prior (``Config.max_tilt``) and the pick order use it.
"""

from __future__ import annotations

import numpy as np

from boxloc.config import Config
from boxloc.scan import Scan

#: Points and hypotheses of the dominant-plane search: enough for a plane covering a tenth
#: of the scan to be found with near certainty, few enough to cost milliseconds.
SAMPLE_POINTS = 4000
RANSAC_TRIALS = 200


def estimate_up(scan: Scan, config: Config, rng: np.random.Generator) -> np.ndarray:
    """Unit up direction (3,) in the sensor frame.

    Parameters
    ----------
    scan : Scan
    config : Config
        The noise model sets the inlier band (3 sigma at the median range).
    rng : numpy.random.Generator
        Seeded from the scan by the pipeline.
    """
    if scan.sensor_to_base is not None:
        return scan.up
    P = scan.points.reshape(-1, 3)
    P = P[np.isfinite(P).all(1)].astype(np.float64)
    if len(P) < 3:
        return scan.up
    if len(P) > SAMPLE_POINTS:
        P = P[np.sort(rng.choice(len(P), SAMPLE_POINTS, replace=False))]
    r = float(np.median(np.linalg.norm(P, axis=1)))
    band = 3.0 * float(config.noise.sigma_range(r)) + config.flatness
    idx = rng.integers(0, len(P), size=(RANSAC_TRIALS, 3))
    A, B, C = P[idx[:, 0]], P[idx[:, 1]], P[idx[:, 2]]
    N = np.cross(B - A, C - A)
    norm = np.linalg.norm(N, axis=1)
    ok = norm > 1e-12
    N, A = N[ok] / norm[ok, None], A[ok]
    if len(N) == 0:
        return scan.up
    D = np.abs((P @ N.T) - np.einsum("ij,ij->i", A, N)[None, :])  # (points, trials)
    counts = (D <= band).sum(0)
    k = int(np.argmax(counts))
    inl = D[:, k] <= band
    Q = P[inl]
    c = Q.mean(0)
    w, V = np.linalg.eigh((Q - c).T @ (Q - c))
    n = V[:, 0]
    if n @ c > 0:  # toward the sensor at the origin
        n = -n
    return n / np.linalg.norm(n)

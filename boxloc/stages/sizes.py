"""Known carton sizes (issue #21, point 2): a rectangle's dimensions against the cell's
carton list (``Config.box_sizes``), and the splits of a flat region into listed cartons.

A rectangle of width w and length l matches listed size (W, L) if

    T = ((w - W)^2 + (l - L)^2) / sigma^2  <=  chi2_{2, 1-alpha}

in the nearer of the two orientations, with sigma = ``Config.size_tolerance`` (SKU_SIZE,
2 dof). A flat region of extent (U, V) along its two axes is nx x ny cartons of size
(a, b) laid along them (a along U) if

    T = (U - nx a)^2 / (nx sigma^2) + (V - ny b)^2 / (ny sigma^2)  <=  chi2_{2, 1-alpha}

(each carton's tolerance independent, so n of them in a row add n sigma^2), nx, ny >= 1
the nearest integers, nx ny >= 2: a multiple (2x1, 3x1, 2x2, ...). Cartons of one layer
are laid one way; a layer of mixed orientations is not a grid and is not split.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from boxloc.stats import chi2_critical

#: Most cartons one flat region is split into (a 1.2 x 0.8 m pallet layer of the smallest
#: cartons a cell handles, 0.15 m, is 8 x 5 = 40).
MAX_PARTS = 64


def size_statistic(w: float, length: float, sizes: tuple[tuple[float, float, float], ...],
                   tolerance: float) -> np.ndarray:
    """SKU_SIZE's statistic against every listed size, (n,) float64 (the nearer of the two
    orientations; sizes are width <= length, so is the nearer one after sorting)."""
    if not sizes:
        return np.zeros(0)
    S = np.asarray([s[:2] for s in sizes], np.float64)
    a, b = sorted((float(w), float(length)))
    t1 = ((a - S[:, 0]) ** 2 + (b - S[:, 1]) ** 2) / tolerance**2
    t2 = ((a - S[:, 1]) ** 2 + (b - S[:, 0]) ** 2) / tolerance**2
    return np.minimum(t1, t2)


def match_size(w: float, length: float, sizes: tuple[tuple[float, float, float], ...],
               tolerance: float, alpha: float) -> tuple[int, float, float, bool]:
    """The listed size nearest a rectangle's dimensions, by SKU_SIZE.

    Returns
    -------
    sku : int
        The row of ``sizes`` with the smallest statistic (-1 if no list).
    statistic, critical : float
        Chi-square, 2 dof, and its critical value at alpha.
    matches : bool
    """
    crit = chi2_critical(2.0, alpha)
    T = size_statistic(w, length, sizes, tolerance)
    if not len(T):
        return -1, np.nan, crit, False
    j = int(np.argmin(T))
    return j, float(T[j]), crit, bool(T[j] <= crit)


@dataclass(frozen=True)
class Split:
    """One way of laying listed cartons over a flat region.

    Attributes
    ----------
    sku : int
        The row of ``Config.box_sizes``.
    a, b : float
        The carton's extent along the region's x and y axes, metres.
    nx, ny : int
        Cartons along x and y.
    statistic : float
        Chi-square (2 dof) of the region's extent against nx a, ny b.
    """

    sku: int
    a: float
    b: float
    nx: int
    ny: int
    statistic: float

    @property
    def parts(self) -> int:
        return self.nx * self.ny

    def cuts(self) -> tuple[list[float], list[float]]:
        """The implied seams' positions along x and y, metres from the region's origin."""
        return ([i * self.a for i in range(1, self.nx)], [j * self.b for j in range(1, self.ny)])


def region_splits(width: float, length: float, sizes: tuple[tuple[float, float, float], ...],
                  tolerance: float, alpha: float, multiples_only: bool = True) -> list[Split]:
    """Every listed size, in either orientation, of which a region of ``width`` x ``length``
    (along its x and y axes, metres) is a grid, by its chi-square at alpha; best first.

    With ``multiples_only`` a single carton (1 x 1) is not a split.
    """
    crit = chi2_critical(2.0, alpha)
    out: list[Split] = []
    for j, (w, ln, _) in enumerate(sizes):
        for a, b in {(w, ln), (ln, w)}:
            nx, ny = max(1, round(width / a)), max(1, round(length / b))
            if nx * ny > MAX_PARTS or (multiples_only and nx * ny < 2):
                continue
            T = ((width - nx * a) ** 2 / nx + (length - ny * b) ** 2 / ny) / tolerance**2
            if T <= crit:
                out.append(Split(j, float(a), float(b), int(nx), int(ny), float(T)))
    out.sort(key=lambda s: (s.statistic, s.sku, s.a))
    return out


def distinct(splits: list[Split]) -> list[Split]:
    """The splits that cut a region differently, best first.

    The parts are measured, the region's extent over the count along each axis
    (:func:`boxloc.stages.hypotheses._plan_split`), so two splits into the same grid
    (nx x ny) cut it at the same places, whichever listed sizes they fit: two sizes within
    the tolerance of each other, or one nearly square carton laid either way (0.534 x 0.545
    m, a region of two of them 1.091 x 0.538 m is 2 x 1 both ways). They are one split,
    the better fitting one.
    """
    out: list[Split] = []
    for s in splits:
        if not any(s.nx == o.nx and s.ny == o.ny for o in out):
            out.append(s)
    return out

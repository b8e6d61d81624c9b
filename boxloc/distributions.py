"""Tail probabilities and quantiles of the tests' null distributions, from ``scipy.special``.

Every function here returns what the ``scipy.stats`` distribution of its name returns, bit
for bit (``tests/test_distributions.py`` compares them over grids), but without importing
``scipy.stats``: that import costs about 0.7 s of CPU, more than a scan, and ``boxloc
locate`` pays it on every call. ``scipy.stats`` evaluates the same special functions behind
its argument handling (``loc`` 0 and ``scale`` 1, whose arithmetic is kept where it can
change a bit: ``x * 1.0 + 0.0`` turns -0.0 into 0.0). The binomial's are the Boost
ufuncs ``scipy.stats.binom`` calls; where a SciPy release lacks them, ``scipy.stats`` is
imported after all.

Arguments are floats or arrays (broadcast); results are float64 of the broadcast shape
(a 0-d array for scalars, as ``scipy.stats`` gives).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
from scipy import special
from scipy.special import _ufuncs

__all__ = ["norm_isf", "norm_sf", "halfnorm_ppf", "t_sf", "chi2_sf", "chi2_isf", "chi2_ppf",
           "poisson_isf", "binom_sf", "binom_isf"]

_BINOM_SF = getattr(_ufuncs, "_binom_sf", None)
_BINOM_ISF = getattr(_ufuncs, "_binom_isf", None)


def _stats() -> Any:
    from scipy import stats

    return stats


def norm_isf(q: float | np.ndarray) -> np.ndarray | np.float64:
    """``scipy.stats.norm.isf(q)``: ``-ndtri(q)`` (inf at 0, -inf at 1, NaN outside).

    scipy computes ``-ndtri(q) * 1.0 + 0.0``; ``0.0 - ndtri(q)`` is the same value,
    including +0.0 at q = 0.5. No argument handling: thousands of calls per scan.
    """
    return 0.0 - special.ndtri(q)


def norm_sf(x: npt.ArrayLike) -> np.ndarray:
    """``scipy.stats.norm.sf(x)``: ``ndtr(-x)``."""
    return np.asarray(special.ndtr(-np.asarray(x, dtype=np.float64)))


def halfnorm_ppf(q: npt.ArrayLike) -> np.ndarray:
    """``scipy.stats.halfnorm.ppf(q)``: ``ndtri((1 + q) / 2)``, for q in [0, 1)."""
    q = np.asarray(q, dtype=np.float64)
    return np.asarray(special.ndtri((1.0 + q) / 2.0) * 1.0 + 0.0)


def t_sf(x: npt.ArrayLike, df: npt.ArrayLike) -> np.ndarray:
    """``scipy.stats.t.sf(x, df)``: ``stdtr(df, -x)``, for finite df > 0."""
    x = np.asarray(x, dtype=np.float64)
    df = np.asarray(df, dtype=np.float64)
    return np.asarray(special.stdtr(df, -(x * 1.0 + 0.0)), dtype=np.float64)


def chi2_sf(x: npt.ArrayLike, df: npt.ArrayLike) -> np.ndarray:
    """``scipy.stats.chi2.sf(x, df)``: ``chdtrc(df, x)``, 1 at and below 0, NaN for NaN."""
    x = np.asarray(x, dtype=np.float64)
    df = np.asarray(df, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        out = special.chdtrc(df, x)
    return np.asarray(np.where(x <= 0.0, 1.0, out), dtype=np.float64)


def chi2_isf(q: npt.ArrayLike, df: npt.ArrayLike) -> np.ndarray:
    """``scipy.stats.chi2.isf(q, df)``: ``chdtri(df, q)``, for q in (0, 1)."""
    q = np.asarray(q, dtype=np.float64)
    return np.asarray(special.chdtri(np.asarray(df, dtype=np.float64), q) * 1.0 + 0.0)


def chi2_ppf(p: npt.ArrayLike, df: npt.ArrayLike) -> np.ndarray:
    """``scipy.stats.chi2.ppf(p, df)``: ``2 gammaincinv(df / 2, p)``, for p in (0, 1)."""
    p = np.asarray(p, dtype=np.float64)
    df = np.asarray(df, dtype=np.float64)
    return np.asarray(2 * special.gammaincinv(df / 2, p) * 1.0 + 0.0)


def poisson_isf(q: float, mu: float) -> float:
    """``scipy.stats.poisson.isf(q, mu)`` for 0 < q < 1 and mu > 0: the smallest count k
    with P(X > k) <= q, by SciPy's ``poisson._ppf(1 - q)`` (``pdtrik``, then a step down
    where ``pdtr`` allows it)."""
    p = 1.0 - q
    vals = np.ceil(special.pdtrik(p, mu))
    vals1 = np.maximum(vals - 1, 0)
    temp = special.pdtr(vals1, mu)
    return float(np.where(temp >= p, vals1, vals) + 0)


def binom_sf(k: npt.ArrayLike, n: npt.ArrayLike, p: float) -> np.ndarray:
    """``scipy.stats.binom.sf(k, n, p)``: P(X > k) for X ~ Binomial(n, p); 1 below 0, 0 at
    and above n (integer n >= 0, p in [0, 1])."""
    if _BINOM_SF is None:
        return np.asarray(_stats().binom.sf(k, n, p), dtype=np.float64)
    k = np.asarray(k, dtype=np.float64)
    n = np.asarray(n)
    inside = (k >= 0) & (k < n)
    with np.errstate(invalid="ignore"):
        val = np.clip(_BINOM_SF(np.floor(k), n, p), 0, 1)
    return np.asarray(np.where(inside, val, np.where(k < 0, 1.0, 0.0)), dtype=np.float64)


def binom_isf(q: float, n: int, p: float) -> float:
    """``scipy.stats.binom.isf(q, n, p)`` for 0 < q < 1: the Boost quantile SciPy uses."""
    if _BINOM_ISF is None:
        return float(_stats().binom.isf(q, n, p))
    return float(_BINOM_ISF(q, n, p) + 0)

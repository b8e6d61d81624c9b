"""boxloc.distributions: scipy.stats's values, bit for bit, without importing scipy.stats."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy import stats as st

from boxloc import distributions as d


def _same(a: object, b: object) -> bool:
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    num = ~np.isnan(a)  # a NaN's sign bit means nothing
    return a.shape == b.shape and np.array_equal(a, b, equal_nan=True) and bool(
        np.all(np.signbit(a[num]) == np.signbit(b[num])))


def test_normal_tails() -> None:
    rng = np.random.default_rng(0)
    q = np.r_[0.0, 1.0, 0.5, 1e-300, 1 - 1e-16, rng.uniform(0, 1, 2000),
              10.0 ** rng.uniform(-12, 0, 2000), np.nan, 1.5]
    assert _same(d.norm_isf(q), st.norm.isf(q))
    for x in (0.3, 0.01 / 7):
        assert _same(d.norm_isf(x), st.norm.isf(x))
    z = np.r_[rng.normal(0, 4, 3000), 0.0, -0.0, np.inf, -np.inf, np.nan]
    assert _same(d.norm_sf(z), st.norm.sf(z))
    assert _same(d.halfnorm_ppf(0.5), st.halfnorm.ppf(0.5))


@pytest.mark.parametrize("df", [1.0, 2.0, 3.0])
def test_chi_square(df: float) -> None:
    rng = np.random.default_rng(int(df))
    x = np.r_[rng.exponential(5.0, 3000), 0.0, -1.0, np.inf, np.nan, 1e-300]
    assert _same(d.chi2_sf(x, df), st.chi2.sf(x, df))
    for a in (0.01, 0.02, 0.05, 0.001, 0.1, rng.uniform(1e-6, 0.5)):
        assert _same(d.chi2_isf(a, df), st.chi2.isf(a, df))
        assert _same(d.chi2_ppf(1.0 - a, df), st.chi2.ppf(1.0 - a, df))


@pytest.mark.parametrize("df", [1.0, 2.5, 4.0, 37.3])
def test_student_t_tail(df: float) -> None:
    rng = np.random.default_rng(int(df * 10))
    x = np.r_[rng.normal(0, 5, 3000), 0.0, -0.0, np.inf, -np.inf, np.nan, 1e3]
    assert _same(d.t_sf(x, df), st.t.sf(x, df))


def test_poisson_quantile() -> None:
    rng = np.random.default_rng(2)
    for _ in range(3000):
        q = float(10.0 ** rng.uniform(-8, -0.5))
        mu = float(10.0 ** rng.uniform(-3, 3))
        assert d.poisson_isf(q, mu) == float(st.poisson.isf(q, mu))


def test_binomial_tails() -> None:
    rng = np.random.default_rng(3)
    for _ in range(3000):
        n = int(rng.integers(0, 30000))
        p = float(rng.choice([0.5, 0.005, 0.0025, rng.uniform(0, 1)]))
        k = int(rng.integers(-2, n + 3))
        assert _same(d.binom_sf(k, n, p), st.binom.sf(k, n, p))
        q = float(rng.choice([0.01, 0.01 / int(rng.integers(1, 300))]))
        assert d.binom_isf(q, n, p) == float(st.binom.isf(q, n, p))
    # the verification's arrays: counts per cell, float from bincount weights
    k = rng.integers(-1, 40, 200).astype(np.float64)
    n = rng.integers(0, 60, 200)
    assert _same(d.binom_sf(k, n, 0.005), st.binom.sf(k, n, 0.005))


def test_a_scan_runs_without_scipy_stats() -> None:
    """``boxloc locate`` does not pay for scipy.stats (~0.7 s of CPU): no stage imports it."""
    code = ("import sys\n"
            "from boxloc.simulate import simulate\n"
            "from boxloc.pipeline import find_graspable_surfaces\n"
            "from boxloc.config import Config\n"
            "before = 'scipy.stats' in sys.modules\n"
            "sim = simulate('pallet:seed=3,width=160,height=120,f=131.25')\n"
            "mods = set(sys.modules)\n"
            "find_graspable_surfaces(sim.scan, Config(min_edge=0.15, max_edge=0.6))\n"
            "print('scipy.stats' in set(sys.modules) - mods)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "False"

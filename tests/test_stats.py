"""The statistical tests: records, and false-alarm rates close to alpha on simulated noise."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats as st

from boxloc.config import Config
from boxloc.products import LineSet
from boxloc.stages.lines import fit_segment
from boxloc.stages.vertices import find_vertices
from boxloc.stats import TestKind, TestTable, chi2_critical, chi2_test


def test_chi2_test_matches_scipy():
    t, crit, p, acc = chi2_test([0.5, 3.0, 10.0], 2.0, 0.05)
    assert crit == pytest.approx(st.chi2.ppf(0.95, 2))
    assert np.allclose(p, st.chi2.sf([0.5, 3.0, 10.0], 2))
    assert acc.tolist() == [True, True, False]
    assert chi2_critical(1.0, 0.01) == pytest.approx(6.6349, abs=1e-4)


def test_table_concat_select_rows():
    a = TestTable.chi2(TestKind.LINES_MEET, [0, 1], [2, 3], [1.0, 9.0], 1.0, 0.01)
    b = TestTable.decision(TestKind.EDGE_SUPPORT, 4, -1, 12.0, 10.0, True, 0.01)
    t = TestTable.concat([a, b], 0.01)
    assert len(t) == 3
    assert t.of_kind(TestKind.LINES_MEET).accepted.tolist() == [True, False]
    rows = t.rows()
    assert rows[2]["kind"] == "EDGE_SUPPORT" and np.isnan(rows[2]["p_value"])
    assert {"statistic", "dof", "critical", "p_value", "alpha", "accepted"} <= set(rows[0])
    assert len(TestTable.concat([], 0.05)) == 0


def _line(c, d, n, length, sigma, rng):
    t = np.linspace(-length / 2, length / 2, n)
    P = c + t[:, None] * d + rng.normal(0, sigma, (n, 3))
    C = np.broadcast_to(sigma**2 * np.eye(3), (n, 3, 3)).copy()
    return fit_segment(P, C)


def _lineset(fits):
    L = len(fits)
    return LineSet(
        points=np.array([f[0] for f in fits]), directions=np.array([f[1] for f in fits]),
        covariances=np.array([f[2] for f in fits]),
        starts=np.array([f[0] + f[3].min() * f[1] for f in fits]),
        ends=np.array([f[0] + f[3].max() * f[1] for f in fits]),
        n_support=np.full(L, 40, np.int32), support_offsets=np.zeros(L + 1, np.int64),
        support=np.zeros(0, np.int32), support_statistic=np.zeros(0, np.float32),
        kinds=np.ones(L, np.uint8), trial=np.zeros(L, np.int32),
        direction_votes=np.zeros(L), position_votes=np.zeros(L), n_trials=0, epsilon=0.0,
        p_success=0.9, seed=0, tests=TestTable.empty(0.05),
    )


@pytest.mark.parametrize("kind", [TestKind.LINES_MEET, TestKind.LINES_ORTHOGONAL])
def test_vertex_tests_false_alarm_rate_is_alpha(kind):
    # two lines that truly meet at right angles: each test rejects with probability alpha
    alpha = 0.05
    cfg = Config(alpha=alpha, angle_tolerance=0.0, flatness=0.0)
    rng = np.random.default_rng(7)
    rejected = 0
    trials = 600
    for _ in range(trials):
        corner = np.array([0.1, -0.05, 1.5])
        a = _line(corner + 0.15 * np.array([1.0, 0, 0]), np.array([1.0, 0, 0]), 40, 0.3,
                  0.002, rng)
        b = _line(corner + 0.15 * np.array([0, 1.0, 0]), np.array([0, 1.0, 0]), 40, 0.3,
                  0.002, rng)
        t = find_vertices(_lineset([a, b]), config=cfg).tests.of_kind(kind)
        rejected += int(not t.accepted[0])
    rate = rejected / trials
    lo, hi = st.binom.interval(0.999, trials, alpha)
    assert lo / trials <= rate <= hi / trials, rate


def test_half_normal_sigma_ignores_a_broad_background():
    from boxloc.stats import half_normal_sigma

    rng = np.random.default_rng(5)
    x = np.r_[np.abs(rng.normal(0.0, 0.7, 4000)), rng.uniform(0.0, 20.0, 400)]
    sigma, kept, k = half_normal_sigma(x, 0.01)
    assert sigma == pytest.approx(0.7, rel=0.05)
    assert k == pytest.approx(2.5758, abs=1e-3)
    assert kept.sum() < len(x) and np.all(x[kept] <= k * sigma)


@pytest.mark.parametrize("n", [1, 2, 7, 256, 512, 701])
def test_nanmedian_last_is_numpys_nanmedian_bit_for_bit(n: int) -> None:
    import warnings

    from boxloc.stats import nanmedian_last

    rng = np.random.default_rng(n)
    for share in (0.0, 0.3, 0.9, 1.0):
        a = rng.standard_normal((3, 11, n)) * 10.0 ** rng.uniform(-4, 2, (3, 11, 1))
        a[rng.random(a.shape) < share] = np.nan
        a[0, 0] = np.round(a[0, 0], 1)  # ties
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows
            ref = np.nanmedian(a, axis=-1)
        got = nanmedian_last(a)
        assert got.shape == ref.shape
        assert np.array_equal(got, ref, equal_nan=True)


def test_a_decision_against_its_numbers_has_a_named_condition() -> None:
    """Every row of a pipeline run whose decision is not what its statistic and critical
    value say by RELATION is of a kind with FURTHER_CONDITIONS, and that names why: so
    ``explain`` never prints a relation its numbers contradict without the reason."""
    from boxloc.pipeline import find_graspable_surfaces
    from boxloc.stats import FURTHER_CONDITIONS, numbers_accept
    from tests.scenes import box, scene

    sim = scene([box(-0.25, 0.0, 0.40, 0.30, 0.25), box(0.2, 0.05, 0.35, 0.45, 0.35),
                 box(0.2, -0.35, 0.35, 0.25, 0.25)], distance=1.6, seed=3)
    r = find_graspable_surfaces(sim.scan, Config())
    n = against = 0
    for product in (r.edges, r.lines, r.vertices, r.hypotheses, r.verification,
                    r.selection, r.surfaces):
        t = getattr(product, "tests", None)
        if t is None:
            continue
        for k, s, c, acc in zip(t.kind, t.statistic, t.critical, t.accepted):
            kind = TestKind(int(k))
            by_numbers = numbers_accept(kind, s, c)
            if by_numbers is None:
                continue
            n += 1
            if by_numbers != bool(acc):
                against += 1
                why = FURTHER_CONDITIONS.get(kind, ("", ""))[0 if acc else 1]
                assert why, (kind.name, s, c, bool(acc))
    assert n > 1000
    assert against > 0  # this scene has such rows (a seam side, a plane end)


def test_numbers_accept_follows_the_kinds_relation() -> None:
    from boxloc.stats import numbers_accept

    assert numbers_accept(TestKind.LINES_MEET, 3.0, 6.6) is True  # chi-square: <=
    assert numbers_accept(TestKind.JUMP, 3.0, 6.6) is False  # a detection: >
    assert numbers_accept(TestKind.VERIFY_INLIERS, 0.8, 0.8) is True  # >=
    assert numbers_accept(TestKind.POINT_ON_PLANE, 361.0, 6.6) is None  # a count
    assert numbers_accept(TestKind.SEAM_PEAK, float("nan"), 3.0) is None

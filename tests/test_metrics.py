"""Tests of kftrack.metrics: definitions, the chi-square bounds' coverage, bad input."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from kftrack import metrics


def test_rmse_scalar_and_vector():
    est = np.array([[1.0, 2.0], [3.0, 4.0]])
    tru = np.zeros((2, 2))
    assert metrics.rmse(tru, est) == pytest.approx(np.sqrt((1 + 4 + 9 + 16) / 4))
    assert metrics.rmse(tru, est, vector=True) == pytest.approx(np.sqrt((5 + 25) / 2))
    np.testing.assert_allclose(metrics.rmse(tru, est, axis=0), np.sqrt([5.0, 10.0]))
    assert metrics.rmse(truth=tru, estimate=est) == metrics.rmse(est, tru)  # (truth, estimate); symmetric
    with pytest.raises(ValueError, match="truth and estimate must have matching shapes"):
        metrics.rmse(np.zeros(3), np.zeros(2))


def test_nees_and_nis_are_mahalanobis_squares_and_broadcast():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(3, 3))
    P = A @ A.T + np.eye(3)
    e = rng.normal(size=(5, 3))
    expected = np.array([v @ np.linalg.inv(P) @ v for v in e])
    np.testing.assert_allclose(metrics.nees(e, np.zeros(3), P), expected, rtol=1e-12)
    np.testing.assert_allclose(metrics.nis(e, P), expected, rtol=1e-12)


def test_nees_of_true_gaussian_errors_is_chi_square():
    """NEES of N(0, P) errors is chi-square(n): Kolmogorov-Smirnov at the 0.1 % level."""
    rng = np.random.default_rng(1)
    P = np.array([[4.0, 1.0], [1.0, 2.0]])
    e = rng.multivariate_normal(np.zeros(2), P, size=4000)
    eps = metrics.nees(e, np.zeros(2), P)
    assert stats.kstest(eps, stats.chi2(2).cdf).pvalue > 1e-3


def test_chi2_bounds_cover_the_stated_probability():
    """The average of N chi-square(d) values falls inside the 95 % bounds in 95 % of trials:
    the count over 4000 trials is checked against its binomial 99.9 % interval."""
    rng = np.random.default_rng(2)
    dof, runs, trials = 4, 50, 4000
    lo, hi = metrics.chi2_bounds(dof, runs, 0.95)
    avg = rng.chisquare(dof, size=(trials, runs)).mean(axis=1)
    inside = np.count_nonzero((avg >= lo) & (avg <= hi))
    b_lo, b_hi = stats.binom(trials, 0.95).ppf([0.0005, 0.9995])
    assert b_lo <= inside <= b_hi


def test_chi2_bounds_values_and_normalization():
    lo, hi = metrics.chi2_bounds(2, 1, 0.95)
    assert lo == pytest.approx(stats.chi2.ppf(0.025, 2)) and hi == pytest.approx(stats.chi2.ppf(0.975, 2))
    # Bar-Shalom et al. (2001) §5.4.2: n = 2, N = 50 runs -> [1.5, 2.6] for the average NEES
    lo, hi = metrics.chi2_bounds(2, 50, 0.95)
    assert (round(lo, 1), round(hi, 1)) == (1.5, 2.6)
    lo, hi = metrics.chi2_bounds(4, 50, 0.95)
    nlo, nhi = metrics.chi2_bounds(4, 50, 0.95, normalize=True)
    assert (nlo, nhi) == pytest.approx((lo / 4, hi / 4))
    assert metrics.anees(np.full(50, 4.0), 4) == pytest.approx(1.0)


@pytest.mark.parametrize("kwargs, match", [
    (dict(dof=0), "dof must be a positive integer"),
    (dict(dof=1.5), "dof must be a positive integer"),
    (dict(runs=0), "runs must be a positive integer"),
    (dict(confidence=1.0), "confidence must lie in"),
])
def test_chi2_bounds_bad_input(kwargs, match):
    args = dict(dof=2, runs=10, confidence=0.95)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        metrics.chi2_bounds(**args)


def test_nees_bad_input():
    with pytest.raises(ValueError, match="truth must have shape"):
        metrics.nees(np.zeros(3), np.zeros(2), np.eye(2))
    with pytest.raises(ValueError, match="P must be positive definite"):
        metrics.nees(np.zeros(2), np.zeros(2), np.diag([1.0, 0.0]))
    with pytest.raises(ValueError, match="dim must be a positive integer"):
        metrics.anees(np.ones(3), 0)


def test_anees_and_rmse_refuse_values_that_cannot_be_right():
    with pytest.raises(ValueError, match="nees_values must be non-negative and finite"):
        metrics.anees(np.array([1.0, -0.5]), 1)
    with pytest.raises(ValueError, match="nees_values must be non-negative and finite"):
        metrics.anees(np.array([1.0, np.inf]), 1)
    with pytest.raises(TypeError, match="estimate must be an array of real numbers"):
        metrics.rmse(np.zeros(1), np.array([1.0 + 1j]))
    assert np.isnan(metrics.anees(np.array([1.0, np.nan]), 1))  # a missing value stays visible


def test_consistency_refuses_a_transposed_array_when_told_the_runs():
    rng = np.random.default_rng(3)
    v = rng.chisquare(2, size=(30, 50))  # T = 30 steps, N = 50 runs
    c = metrics.consistency(v, 2, runs=50)
    assert c.runs == 50 and c.steps == 30 and np.array_equal(c.mean, metrics.consistency(v, 2).mean)
    with pytest.raises(ValueError, match=r"values must have shape \(T, N\) = \(T, 50\).*transposed, \(N, T\): pass values.T"):
        metrics.consistency(v.T, 2, runs=50)
    with pytest.raises(ValueError, match=r"values must have shape \(T, N\) = \(T, 40\)"):
        metrics.consistency(v, 2, runs=40)
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="runs must be a positive integer"):
            metrics.consistency(v, 2, runs=bad)

"""Tests of kftrack.montecarlo: noisy runs, per-run errors, paired differences, comparisons."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from kftrack import models, montecarlo as mc
from kftrack.kalman import kalman_filter


def test_noisy_runs_shape_and_chi_square():
    rng = np.random.default_rng(0)
    clean = np.cumsum(np.ones((50, 2)), axis=0)
    sigma = np.array([2.0, 0.5])
    zs = mc.noisy_runs(rng, clean, sigma, 400)
    assert zs.shape == (50, 400, 2)
    # sum of squared normalized errors is chi-square with T*N dof per component (99 % bounds)
    for i in range(2):
        s = np.sum(((zs[..., i] - clean[:, None, i]) / sigma[i]) ** 2)
        dof = zs[..., i].size
        assert stats.chi2.ppf(0.005, dof) < s < stats.chi2.ppf(0.995, dof)


def test_noisy_runs_seeded_and_zero_sigma():
    clean = np.arange(6.0).reshape(3, 2)
    a = mc.noisy_runs(np.random.default_rng(3), clean, 1.0, 5)
    b = mc.noisy_runs(np.random.default_rng(3), clean, 1.0, 5)
    assert np.array_equal(a, b)
    assert np.array_equal(mc.noisy_runs(np.random.default_rng(3), clean, 0.0, 2), np.stack([clean] * 2, axis=1))


@pytest.mark.parametrize("kwargs, word", [
    (dict(clean=np.zeros(5), sigma=1.0, runs=3), "clean"),
    (dict(clean=np.zeros((5, 2)), sigma=[1.0, 2.0, 3.0], runs=3), "sigma"),
    (dict(clean=np.zeros((5, 2)), sigma=-1.0, runs=3), "sigma"),
    (dict(clean=np.zeros((5, 2)), sigma=1.0, runs=0), "runs"),
    (dict(clean=np.zeros((5, 2)), sigma=1.0, runs=2.5), "runs"),
])
def test_noisy_runs_bad_input(kwargs, word):
    with pytest.raises(ValueError, match=word):
        mc.noisy_runs(np.random.default_rng(0), **kwargs)


def test_noisy_runs_rng_type():
    with pytest.raises(TypeError, match="rng"):
        mc.noisy_runs(0, np.zeros((3, 1)), 1.0, 2)


def test_per_run_error_exact():
    truth = np.zeros((4, 4))
    est = np.zeros((4, 2, 4))
    est[:, 0, 0] = 3.0
    est[:, 0, 2] = 4.0  # distance 5 in run 0
    est[:, 1, 1] = 7.0  # only a velocity error in run 1
    e = mc.per_run_error(truth, est, [0, 2])
    assert np.allclose(e, [25.0, 0.0])
    assert np.allclose(mc.per_run_error(truth, est, [0, 2], root=True), [5.0, 0.0])
    assert np.allclose(mc.per_run_error(truth, est), [25.0, 49.0])
    est[0, 0, 0] = 100.0
    assert np.allclose(mc.per_run_error(truth, est, [0, 2], start=1), [25.0, 0.0])


@settings(max_examples=40, deadline=None)
@given(st.integers(2, 20), st.integers(1, 6), st.integers(0, 10_000))
def test_per_run_error_matches_rmse_squared(T, runs, seed):
    from kftrack.metrics import rmse

    rng = np.random.default_rng(seed)
    est, truth = rng.normal(size=(T, runs, 3)), rng.normal(size=(T, 3))
    e = mc.per_run_error(truth, est, [0, 1])
    assert np.allclose(e, rmse(truth[:, None, :2], est[..., :2], axis=0, vector=True) ** 2, rtol=1e-12)
    assert np.all(e >= 0)


@pytest.mark.parametrize("args, word", [
    ((np.zeros((4, 4)), np.zeros((3, 2, 4))), "time axis"),
    ((np.zeros((3, 5)), np.zeros((3, 2, 4))), "truth"),
    ((np.zeros((3, 4)), np.zeros((3, 2, 5)), [4]), "components"),
    ((np.zeros((3, 4)), np.zeros((3, 2, 4)), [7]), "components"),
    # the old order (estimate, truth): truth with more axes than the estimate is refused
    ((np.zeros((3, 2, 4)), np.zeros((3, 4))), r"order is per_run_error\(truth, estimate"),
])
def test_per_run_error_bad_input(args, word):
    with pytest.raises(ValueError, match=word):
        mc.per_run_error(*args)


def test_per_run_error_bad_start():
    with pytest.raises(ValueError, match="start"):
        mc.per_run_error(np.zeros((3, 4)), np.zeros((3, 2, 4)), start=3)


def test_paired_difference_exact_and_null_distribution():
    d = mc.paired_difference([3.0, 5.0, 4.0], [1.0, 2.0, 3.0])
    assert d.mean == pytest.approx(2.0) and d.se == pytest.approx(1.0 / np.sqrt(3)) and d.runs == 3
    assert d.z == pytest.approx(2.0 * np.sqrt(3))
    # two equally good "filters": z is about standard normal; over 400 repetitions the
    # fraction with |z| > 1.96 is binomial(400, 0.05): inside its 99.9 % range
    rng = np.random.default_rng(7)
    zs = np.array([mc.paired_difference(rng.normal(size=100), rng.normal(size=100)).z for _ in range(400)])
    k = int(np.sum(np.abs(zs) > 1.96))
    lo, hi = stats.binom.ppf([0.0005, 0.9995], 400, 0.05)
    assert lo <= k <= hi


def test_paired_difference_bad_input():
    with pytest.raises(ValueError, match="a and b"):
        mc.paired_difference([1.0, 2.0], [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="a"):
        mc.paired_difference([np.nan, 1.0], [1.0, 2.0])


def test_comparison_statistics_and_readonly():
    c = mc.Comparison({"good": [1.0, 2.0, 3.0, 4.0], "bad": [2.0, 4.0, 6.0, 8.0]})
    assert c.names == ("good", "bad") and c.runs == 4
    assert c.mean("bad") == pytest.approx(5.0)
    assert c.std("good") == pytest.approx(np.std([1, 2, 3, 4], ddof=1))
    assert c.sem("good") == pytest.approx(c.std("good") / 2.0)
    assert c.percentile("good", 2.5) == pytest.approx(0.5)
    assert c.ranking() == ("good", "bad")
    assert c.paired("good", "bad").z < 0
    with pytest.raises(ValueError):
        c.values["good"][0] = 9.0
    with pytest.raises(ValueError, match="name"):
        c.mean("ugly")
    with pytest.raises(ValueError, match="values"):
        mc.Comparison({"a": [1.0, 2.0], "b": [1.0]})


def test_compare_and_run_filters_on_a_kalman_bank():
    """End to end: a CV Kalman filter beats the raw measurements by many standard errors, and the
    raw-measurement error passes its chi-square test."""
    rng = np.random.default_rng(11)
    cv = models.ConstantVelocity(ndim=2, q=0.01)
    T, dt, sigma = 80, 1.0, 3.0
    truth = np.zeros((T, 4))
    truth[:, 0] = 2.0 * np.arange(T)
    truth[:, 1] = 2.0
    zs = mc.noisy_runs(rng, truth[:, [0, 2]], sigma, 200)
    R = sigma**2 * np.eye(2)
    x0, P0 = np.zeros(4), np.diag([100.0, 10.0, 100.0, 10.0])

    def raw(z):
        out = np.zeros(z.shape[:-1] + (4,))
        out[..., [0, 2]] = z
        return out

    est = mc.run_filters({"KF": lambda z: kalman_filter(z, x0, P0, cv.F(dt), cv.Q(dt), cv.H, R), "raw": raw}, zs)
    assert est["KF"].shape == (T, 200, 4)
    c = mc.compare(truth, est, [0, 2])
    assert c.paired("KF", "raw").z < -10
    total = c.mean("raw") * c.runs * T / sigma**2  # chi-square with 2 T N dof
    assert stats.chi2.ppf(0.005, 2 * T * c.runs) < total < stats.chi2.ppf(0.995, 2 * T * c.runs)


def test_run_filters_bad_input():
    with pytest.raises(TypeError, match="filters"):
        mc.run_filters({}, np.zeros((2, 1, 1)))
    with pytest.raises(TypeError, match="filters"):
        mc.run_filters({"a": 3}, np.zeros((2, 1, 1)))
    with pytest.raises(TypeError, match="estimates"):
        mc.compare(np.zeros((2, 1)), [])
    with pytest.raises(TypeError, match=r"order is compare\(truth, estimates"):
        mc.compare({"KF": np.zeros((2, 1, 1))}, np.zeros((2, 1)))


def test_per_run_error_estimate_with_extra_components():
    """An estimate with a turn rate appended is compared on the shared components."""
    truth = np.zeros((3, 4))
    est = np.zeros((3, 2, 5))
    est[..., 4] = 9.0  # omega: not in the truth, not compared
    est[:, 1, 2] = 2.0
    assert np.allclose(mc.per_run_error(truth, est, [0, 2]), [0.0, 4.0])
    with pytest.raises(ValueError, match="truth"):
        mc.per_run_error(truth, est)

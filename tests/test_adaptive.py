"""Tests of kftrack.adaptive: the windowed NIS statistic against its definition, its false-alarm
rate against the binomial bound for chi-square NIS, the adaptive-Q filter equal to the Kalman
filter when it cannot adapt, faster than it on a manoeuvre, and bad input."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from kftrack import adaptive, kalman
from kftrack.models import ConstantVelocity


def test_window_statistic_and_threshold_match_definition():
    rng = np.random.default_rng(1)
    nis = rng.chisquare(2, size=(12, 3))
    nis[4, 1] = np.nan
    d = adaptive.detect_manoeuvre(nis, 2, window=4, confidence=0.95)
    for k in range(12):
        for j in range(3):
            w = nis[max(0, k - 3):k + 1, j]
            w = w[~np.isnan(w)]
            assert d.statistic[k, j] == pytest.approx(w.sum(), rel=1e-13)
            assert d.threshold[k, j] == pytest.approx(stats.chi2.ppf(0.95, 2 * w.size), rel=1e-13)
    assert np.array_equal(d.detected, d.statistic > d.threshold)


@pytest.mark.parametrize("window", [1, 5])
def test_false_alarm_rate_within_binomial_bounds(window):
    rng = np.random.default_rng(20 + window)
    N, conf = 40_000, 0.99
    nis = rng.chisquare(2, size=(8, N))  # a consistent filter's NIS: white chi2(2)
    d = adaptive.detect_manoeuvre(nis, 2, window=window, confidence=conf)
    # at a fixed step the N runs are independent: the alarm count is binomial(N, 1 - conf)
    lo, hi = stats.binom.ppf([0.0005, 0.9995], N, 1 - conf)
    assert lo <= d.detected[-1].sum() <= hi


def _manoeuvre(rng, runs):
    cv = ConstantVelocity(ndim=2, q=0.1)
    dt, T = 1.0, 60
    F, Q = cv.F(dt), cv.Q(dt)
    G = np.array([[dt**2 / 2, 0], [dt, 0], [0, dt**2 / 2], [0, dt]])
    x = np.tile([0.0, 20.0, 0.0, 0.0], (runs, 1))
    truth = np.empty((T, runs, 4))
    for k in range(T):
        truth[k] = x
        a = np.array([0.0, 15.0]) if 20 <= k < 30 else np.zeros(2)
        x = x @ F.T + G @ a + rng.multivariate_normal(np.zeros(4), Q, size=runs)
    zs = truth[..., [0, 2]] + 5.0 * rng.normal(size=(T, runs, 2))
    return truth, zs, F, Q, cv.H, 25.0 * np.eye(2)


def test_boost_one_is_the_kalman_filter():
    truth, zs, F, Q, H, R = _manoeuvre(np.random.default_rng(2), 5)
    x0, P0 = truth[0, 0], np.diag([25.0, 4.0, 25.0, 4.0])
    a = adaptive.adaptive_q_filter(zs, x0, P0, F, Q, H, R, boost=1.0)
    k = kalman.kalman_filter(zs, x0, P0, F, Q, H, R)
    for name in ("x", "P", "nis", "x_prior", "P_prior"):
        assert np.array_equal(getattr(a, name), getattr(k, name)), name
    assert a.detected.any()  # the test fires on the manoeuvre even when Q is not boosted
    # the flags are the windowed test of the filter's own NIS
    assert np.array_equal(a.detected, adaptive.detect_manoeuvre(k.nis, 2, window=3).detected)


def test_adaptive_filter_follows_a_manoeuvre_better():
    runs = 300
    truth, zs, F, Q, H, R = _manoeuvre(np.random.default_rng(3), runs)
    x0, P0 = truth[0, 0], np.diag([25.0, 4.0, 25.0, 4.0])
    a = adaptive.adaptive_q_filter(zs, x0, P0, F, Q, H, R, window=3, confidence=0.99, boost=100.0)
    k = kalman.kalman_filter(zs, x0, P0, F, Q, H, R)
    sl = slice(22, 35)  # the manoeuvre (steps 20-29) and its aftermath
    e2 = {n: np.sum((r.x[sl][..., [0, 2]] - truth[sl][..., [0, 2]]) ** 2, -1).mean(0) for n, r in (("a", a), ("k", k))}
    d = e2["k"] - e2["a"]  # paired over runs
    assert d.mean() > 5 * d.std(ddof=1) / np.sqrt(runs)
    # before the manoeuvre the test fires at most at about its false-alarm rate (one-sided: P0 is wider
    # than the truth's zero initial spread, so the early NIS are smaller than chi2(2) and a two-sided
    # test would not hold; each flag is then a test of level at most 1 %; flags less than w = 3 steps
    # apart share NIS values, so the variance of their mean is at most (2w - 1) times the binomial one:
    # normal bound, 99.95 %)
    early = a.detected[5:18]
    hi = 0.01 + stats.norm.ppf(0.9995) * np.sqrt(0.01 * 0.99 * 5 / early.size)
    assert early.mean() <= hi
    assert a.detected[25:30].mean() > 0.9  # and almost always during the turn


@pytest.mark.parametrize("kwargs, match", [({"window": 0}, "window"), ({"window": 2.5}, "window"),
                                           ({"confidence": 1.0}, "confidence"), ({"boost": 0.5}, "boost"),
                                           ({"boost": np.inf}, "boost")])
def test_bad_input_names_the_argument(kwargs, match):
    truth, zs, F, Q, H, R = _manoeuvre(np.random.default_rng(4), 2)
    with pytest.raises(ValueError, match=match):
        adaptive.adaptive_q_filter(zs, truth[0, 0], np.eye(4), F, Q, H, R, **kwargs)


def test_detect_bad_input():
    with pytest.raises(ValueError, match="nis"):
        adaptive.detect_manoeuvre(np.array([1.0, -1.0]), 1)
    with pytest.raises(ValueError, match="dof"):
        adaptive.detect_manoeuvre(np.ones(3), 0)
    with pytest.raises(ValueError, match="window"):
        adaptive.detect_manoeuvre(np.ones(3), 1, window=-2)

"""Tests of irregular sampling and time-varying transitions in kftrack.kalman: the filter against
a hand-rolled loop of public single steps, the three forms of F, Q against each other, the RTS
smoother against the brute-force joint Gaussian posterior, missing rows, and bad input."""
from __future__ import annotations

import numpy as np
import pytest

from kftrack import kalman
from kftrack.models import ConstantVelocity

EPS = np.finfo(float).eps
MODEL = ConstantVelocity(ndim=2, q=0.7)
H = MODEL.H
R = np.diag([4.0, 2.5])


def problem(rng, T=12, runs=3, missing=True):
    dts = rng.choice([0.4, 1.0, 1.7, 2.5], size=T)
    zs = rng.normal(scale=5.0, size=(T, runs, 2)).cumsum(0)
    if missing:
        zs[3] = np.nan  # every run misses step 3
        zs[5, 1] = np.nan  # run 1 misses step 5
        zs[T - 1, 0] = np.nan  # and run 0 the last step
    x0 = np.array([1.0, 0.5, -2.0, 1.0])
    P0 = np.diag([30.0, 5.0, 20.0, 4.0])
    return dts, zs, x0, P0


def hand_rolled(zs, x0, P0, dts):
    """The filter written out with the public single steps: update (unless missing), then predict
    with F(dt_k), Q(dt_k)."""
    T, runs = zs.shape[:2]
    x = np.broadcast_to(x0, (runs, 4)).copy()
    P = np.broadcast_to(P0, (runs, 4, 4)).copy()
    xs, Ps, xp, Pp = (np.empty((T, runs, 4)), np.empty((T, runs, 4, 4)), np.empty((T, runs, 4)),
                      np.empty((T, runs, 4, 4)))
    for k in range(T):
        xp[k], Pp[k] = x, P
        for i in range(runs):
            if not np.isnan(zs[k, i]).all():
                u = kalman.update(x[i], P[i], zs[k, i], H, R)
                x[i], P[i] = u.x, u.P
        xs[k], Ps[k] = x, P
        if k < T - 1:
            for i in range(runs):
                x[i], P[i] = kalman.predict(x[i], P[i], MODEL.F(dts[k]), MODEL.Q(dts[k]))
    return xp, Pp, xs, Ps


def test_irregular_dt_is_the_hand_rolled_loop():
    # the same kernels, the same operations in the same order: equal to the last bit
    dts, zs, x0, P0 = problem(np.random.default_rng(1))
    res = kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, dt=dts)
    for a, b in zip((res.x_prior, res.P_prior, res.x, res.P), hand_rolled(zs, x0, P0, dts)):
        assert np.array_equal(a, b)
    assert np.isnan(res.nis[3]).all() and np.isnan(res.nis[5, 1]) and np.isfinite(res.nis[5, 0])


def test_dt_form_time_varying_form_and_constant_form_agree():
    dts, zs, x0, P0 = problem(np.random.default_rng(2))
    a = kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, dt=dts)
    Fs = np.stack([MODEL.F(d) for d in dts])
    Qs = np.stack([MODEL.Q(d) for d in dts])
    b = kalman.kalman_filter(zs, x0, P0, Fs, Qs, H, R, time_varying=True)
    assert all(np.array_equal(u, v, equal_nan=True) for u, v in zip(a, b))
    # one interval: the dt form is the constant form; a constant stack is the same arithmetic
    c = kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, dt=1.7)
    d = kalman.kalman_filter(zs, x0, P0, MODEL.F(1.7), MODEL.Q(1.7), H, R)
    T = zs.shape[0]
    e = kalman.kalman_filter(zs, x0, P0, np.broadcast_to(MODEL.F(1.7), (T, 4, 4)),
                             np.broadcast_to(MODEL.Q(1.7), (T, 4, 4)), H, R, time_varying=True)
    for u, v, w in zip(c, d, e):
        assert np.array_equal(u, v, equal_nan=True)
        # identical operations, so equal; allow the round-off bound T * n * eps * |x| should a BLAS
        # ever order a batched product differently from an unbatched one
        assert np.allclose(u, w, rtol=T * 4 * EPS * 10, atol=0, equal_nan=True)


def test_callables_are_evaluated_once_per_distinct_interval():
    calls = []

    def F(dt):
        calls.append(dt)
        return MODEL.F(dt)

    dts, zs, x0, P0 = problem(np.random.default_rng(3))
    kalman.kalman_filter(zs, x0, P0, F, MODEL.Q, H, R, dt=dts)
    assert sorted(calls) == sorted(set(dts.tolist()))


def joint_posterior(zs, x0, P0, Fs, Qs):
    """Brute force: the joint Gaussian posterior of (x_0, ..., x_{T-1}) of one run in information
    form, Lambda X = eta, solved in one dense solve; returns means (T, n), marginal covariances
    (T, n, n) and cond(Lambda)."""
    T, n = zs.shape[0], x0.size
    N = T * n
    Lam, eta = np.zeros((N, N)), np.zeros(N)
    blk = lambda k: slice(k * n, (k + 1) * n)  # noqa: E731
    P0i = np.linalg.inv(P0)
    Lam[blk(0), blk(0)] += P0i
    eta[blk(0)] += P0i @ x0
    Ri = np.linalg.inv(R)
    for k in range(T):
        if not np.isnan(zs[k]).all():
            Lam[blk(k), blk(k)] += H.T @ Ri @ H
            eta[blk(k)] += H.T @ Ri @ zs[k]
        if k < T - 1:  # x_{k+1} - F_k x_k ~ N(0, Q_k)
            Qi = np.linalg.inv(Qs[k])
            A = np.zeros((n, N))
            A[:, blk(k)] = -Fs[k]
            A[:, blk(k + 1)] = np.eye(n)
            Lam += A.T @ Qi @ A
    mean = np.linalg.solve(Lam, eta)
    cov = np.linalg.inv(Lam)
    return (mean.reshape(T, n), np.stack([cov[blk(k), blk(k)] for k in range(T)]), np.linalg.cond(Lam))


@pytest.mark.parametrize("form", ["dt", "time_varying"])
def test_smoother_is_the_joint_gaussian_posterior(form):
    rng = np.random.default_rng(4)
    dts, zs, x0, P0 = problem(rng, T=8, runs=2)
    Fs = np.stack([MODEL.F(d) for d in dts])
    Qs = np.stack([MODEL.Q(d) for d in dts])
    if form == "dt":
        res = kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, dt=dts)
        sm = kalman.rts_smoother(res, MODEL.F, dt=dts)
    else:
        res = kalman.kalman_filter(zs, x0, P0, Fs, Qs, H, R, time_varying=True)
        sm = kalman.rts_smoother(res, Fs, time_varying=True)
    for i in range(zs.shape[1]):
        mean, cov, cond = joint_posterior(zs[:, i], x0, P0, Fs, Qs)
        # both are backward-stable solutions of the same linear system of size N = T n:
        # |error| <= c N cond(Lambda) eps |x|, with c = 10 for the constants of LU and the recursion
        N = zs.shape[0] * 4
        tol = 10 * N * cond * EPS
        assert np.max(np.abs(sm.x[:, i] - mean)) <= tol * np.max(np.abs(mean))
        assert np.max(np.abs(sm.P[:, i] - cov)) <= tol * np.max(np.abs(cov))
        assert tol < 1e-6  # the bound is informative


def test_shared_covariances_are_read_only_views_equal_to_batched():
    dts, zs, x0, P0 = problem(np.random.default_rng(5), missing=False)
    a = kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, dt=dts)
    b = kalman.kalman_filter(zs, x0, np.broadcast_to(P0, (3, 4, 4)), MODEL.F, MODEL.Q, H, R, dt=dts)
    assert all(np.array_equal(u, v) for u, v in zip(a, b))
    assert a.P.shape == (zs.shape[0], 3, 4, 4) and not a.P.flags.writeable
    sa, sb = kalman.rts_smoother(a, MODEL.F, dt=dts), kalman.rts_smoother(b, MODEL.F, dt=dts)
    assert all(np.array_equal(u, v) for u, v in zip(sa, sb))


def test_bad_transition_forms_are_named():
    dts, zs, x0, P0 = problem(np.random.default_rng(6))
    T = zs.shape[0]
    with pytest.raises(TypeError, match="^F is a callable"):
        kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R)
    with pytest.raises(TypeError, match="^F must be a callable of the interval dt"):
        kalman.kalman_filter(zs, x0, P0, MODEL.F(1.0), MODEL.Q, H, R, dt=dts)
    with pytest.raises(TypeError, match="^Q must be a callable of the interval dt"):
        kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q(1.0), H, R, dt=dts)
    with pytest.raises(ValueError, match="^dt and time_varying=True exclude each other"):
        kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, dt=dts, time_varying=True)
    with pytest.raises(ValueError, match=r"^dt must be a scalar or have shape \(12,\).* or \(11,\).*shape \(10,\)$"):
        kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, dt=dts[:-2])
    with pytest.raises(ValueError, match=r"^dt must be >= 0 \(intervals in s\), but dt\[0\] = -"):
        kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, dt=-dts)
    with pytest.raises(ValueError, match="^dt must be finite"):
        kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, dt=np.full(T, np.nan))
    with pytest.raises(ValueError, match=r"^F must have shape \(T, \.\.\., 4, 4\) with T = 12"):
        kalman.kalman_filter(zs, x0, P0, np.stack([MODEL.F(1.0)] * (T - 1)), np.stack([MODEL.Q(1.0)] * T),
                             H, R, time_varying=True)
    with pytest.raises(ValueError, match=r"^Q must have shape \(T, \.\.\., 4, 4\)"):
        kalman.kalman_filter(zs, x0, P0, np.stack([MODEL.F(1.0)] * T), MODEL.Q(1.0), H, R, time_varying=True)
    with pytest.raises(ValueError, match=r"^Q\(dt\) must be positive semi-definite"):
        kalman.kalman_filter(zs, x0, P0, MODEL.F, lambda d: -MODEL.Q(d), H, R, dt=dts)
    with pytest.raises(ValueError, match=r"^F\(dt\) must have shape \(\.\.\., 4, 4\)"):
        kalman.kalman_filter(zs, x0, P0, lambda d: np.eye(3), MODEL.Q, H, R, dt=dts)
    with pytest.raises(TypeError, match="^time_varying must be True or False"):
        kalman.kalman_filter(zs, x0, P0, MODEL.F(1.0), MODEL.Q(1.0), H, R, time_varying="yes")
    res = kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, dt=dts)
    with pytest.raises(TypeError, match="^F must be a callable of the interval dt"):
        kalman.rts_smoother(res, MODEL.F(1.0), dt=dts)
    with pytest.raises(TypeError, match="^F is a callable"):
        kalman.rts_smoother(res, MODEL.F)
    with pytest.raises(ValueError, match=r"^F must have shape \(T, \.\.\., 4, 4\)"):
        kalman.rts_smoother(res, MODEL.F(1.0), time_varying=True)


def test_intervals_of_length_T_minus_1_and_timestamps_are_the_same_filter():
    # np.diff(t) (T - 1 intervals) and times=t give the filter of dt (T,): the last interval is never
    # used (no step follows), so every number is the same, bit for bit; the smoother likewise
    dts, zs, x0, P0 = problem(np.random.default_rng(8))
    t = np.concatenate([[100.0], 100.0 + np.cumsum(dts[:-1])])  # timestamps whose diff is dts[:-1]
    ref = kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, dt=dts)
    for kw in (dict(dt=dts[:-1]), dict(times=t)):
        res = kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, **kw)
        sm, sm_ref = kalman.rts_smoother(res, MODEL.F, **kw), kalman.rts_smoother(ref, MODEL.F, dt=dts)
        if "dt" in kw:
            assert all(np.array_equal(a, b, equal_nan=True) for a, b in zip(res, ref))
            assert all(np.array_equal(a, b) for a, b in zip(sm, sm_ref))
        else:  # np.diff(t) rounds each interval to an ulp of t (~100 s: 1.4e-14 s)
            assert np.abs(np.diff(t) - dts[:-1]).max() <= 2 * 128 * EPS
            # a relative change d of the intervals changes F, Q by O(d); the filter is stable, so the
            # estimates move by O(d) relative to their scale: 1e4 * d covers constants and T = 12 steps
            d = 2 * 128 * EPS / dts.min()
            np.testing.assert_allclose(res.x, ref.x, rtol=0, atol=1e4 * d * np.abs(ref.x).max())
            np.testing.assert_allclose(sm.x, sm_ref.x, rtol=0, atol=1e4 * d * np.abs(sm_ref.x).max())


def test_times_is_checked_and_excludes_dt():
    dts, zs, x0, P0 = problem(np.random.default_rng(9))
    T = zs.shape[0]
    t = np.cumsum(dts)
    with pytest.raises(ValueError, match="^dt and times exclude each other"):
        kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, dt=dts, times=t)
    with pytest.raises(ValueError, match=rf"^times must have shape \({T},\).*got shape \({T - 1},\)$"):
        kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, times=t[1:])
    with pytest.raises(ValueError, match=r"^times must be non-decreasing, but times\[2\] < times\[1\]"):
        kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, times=np.r_[0.0, 2.0, 1.0, t[3:]])
    with pytest.raises(ValueError, match="^times must be finite"):
        kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, times=np.full(T, np.nan))
    with pytest.raises(ValueError, match="^times and time_varying=True exclude each other"):
        kalman.kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, times=t, time_varying=True)
    with pytest.raises(TypeError, match="^F must be a callable of the interval dt .* when times is given"):
        kalman.kalman_filter(zs, x0, P0, MODEL.F(1.0), MODEL.Q, H, R, times=t)

"""Tests of kftrack.kalman: algebra against filterpy (test-only oracle) and closed forms,
batch broadcasting, missing measurements, the RTS smoother, consistency by chi-square bounds,
and bad input."""
from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from filterpy.kalman import rts_smoother as fp_rts
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from kftrack import kalman
from kftrack.metrics import chi2_bounds

EPS = np.finfo(float).eps


def random_spd(rng, n, scale=1.0):
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T + n * np.eye(n))


def random_system(rng, n=4, m=2):
    F = np.eye(n) + 0.3 * rng.normal(size=(n, n))
    H = rng.normal(size=(m, n))
    return F, random_spd(rng, n, 0.1), H, random_spd(rng, m)


def cv2d(dt=1.0, q=0.5, r=4.0):
    """2-D constant velocity, state [x, vx, y, vy] (test fixture, written out by hand)."""
    Fa = np.array([[1.0, dt], [0.0, 1.0]])
    Qa = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    F = np.kron(np.eye(2), Fa)
    Q = np.kron(np.eye(2), Qa)
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    return F, Q, H, r * np.eye(2)


def simulate(rng, F, Q, H, R, x0, P0, steps, runs):
    n, m = F.shape[0], H.shape[0]
    x = rng.multivariate_normal(x0, P0, size=runs)
    xs, zs = np.empty((steps, runs, n)), np.empty((steps, runs, m))
    for k in range(steps):
        xs[k] = x
        zs[k] = x @ H.T + rng.multivariate_normal(np.zeros(m), R, size=runs)
        x = x @ F.T + rng.multivariate_normal(np.zeros(n), Q, size=runs)
    return xs, zs


# --- algebra ---------------------------------------------------------------------------


def test_predict_and_update_match_filterpy():
    rng = np.random.default_rng(1)
    F, Q, H, R = random_system(rng)
    x, P = rng.normal(size=4), random_spd(rng, 4)
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.x, kf.P, kf.F, kf.Q, kf.H, kf.R = x.copy(), P.copy(), F, Q, H, R
    kf.predict()
    xp, Pp = kalman.predict(x, P, F, Q)
    np.testing.assert_allclose(xp, kf.x, rtol=1e-12)
    np.testing.assert_allclose(Pp, kf.P, rtol=1e-12)
    z = rng.normal(size=2)
    kf.update(z)
    u = kalman.update(xp, Pp, z, H, R)
    np.testing.assert_allclose(u.x, kf.x, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(u.P, kf.P, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(u.y, kf.y, rtol=1e-12)
    np.testing.assert_allclose(u.S, kf.S, rtol=1e-12)
    np.testing.assert_allclose(u.K, kf.K, rtol=1e-10)
    np.testing.assert_allclose(u.loglik, kf.log_likelihood, rtol=1e-10)
    np.testing.assert_allclose(u.nis, kf.mahalanobis**2, rtol=1e-10)


def test_update_equals_information_form_and_loglik_equals_scipy():
    rng = np.random.default_rng(2)
    F, Q, H, R = random_system(rng, 5, 3)
    x, P, z = rng.normal(size=5), random_spd(rng, 5), rng.normal(size=3)
    u = kalman.update(x, P, z, H, R)
    # information form: P+^{-1} = P^{-1} + H^T R^{-1} H; x+ = P+ (P^{-1} x + H^T R^{-1} z)
    P_info = np.linalg.inv(np.linalg.inv(P) + H.T @ np.linalg.solve(R, H))
    x_info = P_info @ (np.linalg.solve(P, x) + H.T @ np.linalg.solve(R, z))
    np.testing.assert_allclose(u.P, P_info, rtol=1e-9)
    np.testing.assert_allclose(u.x, x_info, rtol=1e-9)
    S = H @ P @ H.T + R
    assert u.loglik == pytest.approx(stats.multivariate_normal(H @ x, S).logpdf(z), rel=1e-12)
    assert u.nis == pytest.approx((z - H @ x) @ np.linalg.solve(S, z - H @ x), rel=1e-12)


def test_batch_equals_loop_with_shared_and_per_batch_matrices():
    rng = np.random.default_rng(3)
    F, Q, H, R = random_system(rng)
    B = 7
    x = rng.normal(size=(B, 4))
    P = np.stack([random_spd(rng, 4) for _ in range(B)])
    Rb = np.stack([random_spd(rng, 2) for _ in range(B)])
    z = rng.normal(size=(B, 2))
    xp, Pp = kalman.predict(x, P, F, Q)
    u = kalman.update(xp, Pp, z, H, Rb)
    for b in range(B):
        xb, Pb = kalman.predict(x[b], P[b], F, Q)
        ub = kalman.update(xb, Pb, z[b], H, Rb[b])
        for field in kalman.Update._fields:
            np.testing.assert_allclose(getattr(u, field)[b], getattr(ub, field), rtol=1e-12, atol=1e-14)
    # two batch axes broadcast against each other
    x2 = np.broadcast_to(x[:, None, :], (B, 3, 4))
    u2 = kalman.update(x2, Pp[:, None], z[None, :3, :].repeat(B, 0), H, R)
    assert u2.x.shape == (B, 3, 4) and u2.nis.shape == (B, 3)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 6), m=st.integers(1, 4),
       scale=st.floats(1e-6, 1e6))
def test_joseph_update_is_symmetric_psd_and_not_larger_than_prior(seed, n, m, scale):
    rng = np.random.default_rng(seed)
    P = random_spd(rng, n, scale)
    H = rng.normal(size=(m, n))
    R = random_spd(rng, m, scale)
    u = kalman.update(rng.normal(size=n), P, rng.normal(size=m), H, R)
    np.testing.assert_array_equal(u.P, u.P.T)
    tol = 1e3 * n * EPS * np.abs(P).max()
    assert np.linalg.eigvalsh(u.P).min() >= -tol
    assert np.linalg.eigvalsh(P - u.P).min() >= -tol  # a measurement never adds uncertainty


# --- sequences ---------------------------------------------------------------------------


def test_kalman_filter_equals_step_by_step_and_nan_row_predicts_only():
    rng = np.random.default_rng(4)
    F, Q, H, R = cv2d()
    x0, P0 = np.zeros(4), 100.0 * np.eye(4)
    _, zs = simulate(rng, F, Q, H, R, x0, P0, 12, 1)
    zs = zs[:, 0]
    zs[5] = np.nan
    res = kalman.kalman_filter(zs, x0, P0, F, Q, H, R)
    x, P = x0, P0
    for k in range(12):
        np.testing.assert_allclose(res.x_prior[k], x, rtol=1e-12)
        if k == 5:
            assert np.isnan(res.nis[k]) and np.isnan(res.loglik[k])
        else:
            u = kalman.update(x, P, zs[k], H, R)
            x, P = u.x, u.P
            assert res.nis[k] == pytest.approx(u.nis, rel=1e-12)
        np.testing.assert_allclose(res.x[k], x, rtol=1e-12)
        np.testing.assert_allclose(res.P[k], P, rtol=1e-12)
        x, P = kalman.predict(x, P, F, Q)


def test_kalman_filter_batch_with_missing_in_some_runs_only():
    rng = np.random.default_rng(5)
    F, Q, H, R = cv2d()
    _, zs = simulate(rng, F, Q, H, R, np.zeros(4), np.eye(4), 10, 3)
    zs[4, 1] = np.nan
    res = kalman.kalman_filter(zs, np.zeros(4), np.eye(4), F, Q, H, R)
    for r in range(3):
        single = kalman.kalman_filter(zs[:, r], np.zeros(4), np.eye(4), F, Q, H, R)
        np.testing.assert_allclose(res.x[:, r], single.x, rtol=1e-12)
        np.testing.assert_allclose(res.P[:, r], single.P, rtol=1e-12)
    assert np.isnan(res.nis[4, 1]) and not np.isnan(res.nis[4, 0])


def test_rts_smoother_matches_filterpy_and_reduces_covariance():
    rng = np.random.default_rng(6)
    F, Q, H, R = cv2d()
    x0, P0 = np.zeros(4), 10.0 * np.eye(4)
    _, zs = simulate(rng, F, Q, H, R, x0, P0, 30, 1)
    res = kalman.kalman_filter(zs[:, 0], x0, P0, F, Q, H, R)
    sm = kalman.rts_smoother(res, F)
    xs_fp, Ps_fp, _, _ = fp_rts(res.x, res.P, [F] * 30, [Q] * 30)
    np.testing.assert_allclose(sm.x, xs_fp, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(sm.P, Ps_fp, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(sm.x[-1], res.x[-1])
    for k in range(29):
        assert np.linalg.eigvalsh(res.P[k] - sm.P[k]).min() >= -1e-10


# --- statistics --------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_nees_and_nis_inside_chi_square_bounds_on_random_systems(seed):
    """A correctly modelled KF is consistent: the Monte Carlo average NEES (NIS) at a fixed
    step lies in its two-sided 99.9 % chi-square interval. With 3 seeds x 2 statistics x 2
    steps the chance of a false failure is below 1.2 %."""
    rng = np.random.default_rng(seed)
    n, m, runs = 4, 2, 500
    F, Q, H, R = random_system(rng, n, m)
    F = F / max(1.0, np.abs(np.linalg.eigvals(F)).max())  # keep it stable
    x0, P0 = rng.normal(size=n), random_spd(rng, n)
    xs, zs = simulate(rng, F, Q, H, R, x0, P0, 20, runs)
    res = kalman.kalman_filter(zs, x0, P0, F, Q, H, R)
    err = xs - res.x
    nees = np.einsum("tri,tri->tr", err, np.linalg.solve(res.P, err[..., None])[..., 0])
    lo_x, hi_x = chi2_bounds(n, runs, 0.999)
    lo_y, hi_y = chi2_bounds(m, runs, 0.999)
    for k in (5, 19):
        assert lo_x <= nees[k].mean() <= hi_x
        assert lo_y <= res.nis[k].mean() <= hi_y


# --- bad input ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(x=np.zeros(3)), "P must have shape"),
        (dict(P=np.array([[1.0, 0.5], [0.0, 1.0]])), "P must be symmetric"),
        (dict(P=np.diag([1.0, -1.0])), "P must be positive semi-definite"),
        (dict(x=np.array([np.nan, 0.0])), "x must be finite"),
        (dict(z=np.array([1.0, 2.0])), "H must have shape"),
        (dict(R=np.zeros((1, 1))), "R must be positive definite"),
        (dict(z=np.array([np.inf])), "z must be finite"),
        (dict(H=np.ones((1, 3))), "H must have shape"),
        (dict(x="abc"), "x must be an array of real numbers"),
    ],
)
def test_update_bad_input_names_the_argument(kwargs, match):
    args = dict(x=np.zeros(2), P=np.eye(2), z=np.array([1.0]), H=np.array([[1.0, 0.0]]), R=np.eye(1))
    args.update(kwargs)
    with pytest.raises((ValueError, TypeError), match=match):
        kalman.update(**args)


def test_predict_bad_input_and_batch_mismatch():
    with pytest.raises(ValueError, match="F must have shape"):
        kalman.predict(np.zeros(2), np.eye(2), np.eye(3), np.eye(2))
    with pytest.raises(ValueError, match="Q must be symmetric"):
        kalman.predict(np.zeros(2), np.eye(2), np.eye(2), np.array([[1.0, 1.0], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="batch axes do not broadcast"):
        kalman.predict(np.zeros((3, 2)), np.eye(2), np.broadcast_to(np.eye(2), (4, 2, 2)), np.eye(2))


def test_kalman_filter_bad_input():
    F, Q, H, R = cv2d()
    zs = np.zeros((5, 2))
    zs[2, 0] = np.nan
    with pytest.raises(ValueError, match="only partly NaN"):
        kalman.kalman_filter(zs, np.zeros(4), np.eye(4), F, Q, H, R)
    with pytest.raises(ValueError, match="zs must have shape \\(T, ..., m\\)"):
        kalman.kalman_filter(np.zeros(2), np.zeros(4), np.eye(4), F, Q, H, R)
    with pytest.raises(ValueError, match="zs must be finite or NaN"):
        kalman.kalman_filter(np.full((3, 2), np.inf), np.zeros(4), np.eye(4), F, Q, H, R)
    with pytest.raises(TypeError, match="result must be a FilterResult"):
        kalman.rts_smoother((1, 2), F)
    res = kalman.kalman_filter(np.zeros((5, 2)), np.zeros(4), np.eye(4), F, Q, H, R)
    with pytest.raises(ValueError, match=r"F must have shape \(4, 4\) or the filter's batch axes"):
        kalman.rts_smoother(res, np.broadcast_to(F, (3, 4, 4)))  # more batch axes than the filter had
    with pytest.raises(ValueError, match="F must have shape"):
        kalman.rts_smoother(res, np.eye(3))


def test_bad_input_says_where_the_expected_sizes_come_from():
    x, P, H, R = np.zeros(2), np.eye(2), np.array([[1.0, 0.0]]), np.eye(1)
    # a measurement of the wrong size: H is blamed, and the message says m comes from z
    with pytest.raises(ValueError, match=r"H must have shape \(\.\.\., 2, 2\), got shape \(1, 2\) \(m = 2 from z, n = 2 from x\)"):
        kalman.update(x, P, np.zeros(2), H, R)
    with pytest.raises(ValueError, match=r"R must have shape \(\.\.\., 1, 1\), got shape \(2, 2\) \(m = 1 from z\)"):
        kalman.update(x, P, np.zeros(1), H, np.eye(2))
    with pytest.raises(ValueError, match=r"F must have shape \(\.\.\., 2, 2\), got shape \(3, 3\) \(n = 2 from x\)"):
        kalman.predict(x, P, np.eye(3), np.eye(2))
    with pytest.raises(ValueError, match=r"batch axes do not broadcast: x \(3,\), P \(4,\).*must be equal or 1"):
        kalman.update(np.zeros((3, 2)), np.broadcast_to(P, (4, 2, 2)), np.zeros(1), H, R)


def test_kalman_filter_names_x0_and_P0():
    F, Q, H, R = cv2d()
    zs = np.zeros((3, 2))
    with pytest.raises(ValueError, match="^x0 must be finite"):
        kalman.kalman_filter(zs, np.array([np.nan, 0, 0, 0]), np.eye(4), F, Q, H, R)
    with pytest.raises(ValueError, match=r"^P0 must have shape \(\.\.\., 4, 4\), got shape \(2, 2\) \(n = 4 from x0\)"):
        kalman.kalman_filter(zs, np.zeros(4), np.eye(2), F, Q, H, R)
    with pytest.raises(ValueError, match="^P0 must be positive semi-definite"):
        kalman.kalman_filter(zs, np.zeros(4), -np.eye(4), F, Q, H, R)
    with pytest.raises(ValueError, match=r"^R must have shape \(\.\.\., 1, 1\), got shape \(2, 2\) \(m = 1 from zs\)"):
        kalman.kalman_filter(np.zeros((3, 1)), np.zeros(4), np.eye(4), F, Q, H, R)


@pytest.mark.parametrize("bad", [None, 1j * np.eye(2), [[1.0, 0.0], [0.0, 1.0 + 1e-9j]]])
def test_none_and_complex_input_is_refused_not_coerced(bad):
    """NumPy would turn None into NaN and drop an imaginary part with only a warning."""
    with pytest.raises(TypeError, match="^F must be an array of real numbers, got (None|complex)"):
        kalman.predict(np.zeros(2), np.eye(2), bad, np.eye(2))

"""The bad-input cases of the newcomer review (../shared/reviews/2026-12-newcomer/bad-input.md) that
land in the linear, extended and unscented filters and the RTS smoother: each raises a clear
error naming the argument (type and message asserted), or, where the input is legitimate, gives
the correct result (checked against an independent computation with a derived bound)."""
from __future__ import annotations

import re

import numpy as np
import pytest

from kftrack import ekf, kalman, models, ukf

EPS = np.finfo(float).eps
nan = np.nan
cv = models.ConstantVelocity(ndim=2, q=1.0)
x = np.zeros(4)
P = 10 * np.eye(4)
F = cv.F(1.0)
Q = cv.Q(1.0)
H = cv.H
R = 4 * np.eye(2)
z = np.array([1.0, 2.0])
zs = np.cumsum(np.ones((20, 2)), 0)
h = lambda s: s[..., [0, 2]]  # noqa: E731
Hj = lambda s: np.broadcast_to(H, s.shape[:-1] + (2, 4))  # noqa: E731
f = lambda s: s @ F.T  # noqa: E731
Fj = lambda s: cv.jacobian(s, 1.0)  # noqa: E731


# --------------------------------------------------------------------------------------------
# single steps
# --------------------------------------------------------------------------------------------
def test_predict_with_an_empty_state_names_x():
    with pytest.raises(ValueError, match=r"^x must have shape \(\.\.\., n\) with n >= 1 .*got shape \(0,\)"):
        kalman.predict(np.zeros(0), np.zeros((0, 0)), np.zeros((0, 0)), np.zeros((0, 0)))


def test_predict_that_overflows_names_P():
    with np.errstate(over="ignore", invalid="ignore"):
        with pytest.raises(ValueError, match=r"^P is too large: the prediction .* overflows float64.*\|P\| = 1e\+308"):
            kalman.predict(x, 1e308 * np.eye(4), F, Q)


def test_update_with_a_huge_innovation_is_correct_and_its_nis_saturates():
    # y^T S^-1 y = (1e200)^2 / 14 exceeds float64: nis = inf and loglik = -inf are the correctly
    # rounded values; the posterior does not overflow and is exact: x = K z with K = P H^T S^-1,
    # S = H P H^T + R = 14 I, so x[0] = (10/14) 1e200 and x[2] = 10/14 (two roundings: 2 eps)
    zbig = np.array([1e200, 1.0])
    with np.errstate(over="ignore"):
        u = kalman.update(x, P, zbig, H, R)
    assert u.nis == np.inf and u.loglik == -np.inf
    np.testing.assert_allclose(u.x, [10 / 14 * 1e200, 0.0, 10 / 14, 0.0], rtol=2 * EPS, atol=0)
    np.testing.assert_array_equal(u.P, kalman.update(x, P, z, H, R).P)  # P does not depend on z


def test_ekf_update_refuses_a_float_angle_index():
    with pytest.raises(TypeError, match=r"^angle_components must be a sequence of integer indices, got \[0\.5\]"):
        ekf.ekf_update(x, P, z, h, Hj, R, angle_components=[0.5])
    with pytest.raises(TypeError, match="^state_angles must be a sequence of integer indices"):
        ekf.ekf_update(x, P, z, h, Hj, R, state_angles=[1.0])
    u = ekf.ekf_update(x, P, z, h, Hj, R, angle_components=np.array([1]))  # a NumPy integer is an index
    assert np.isfinite(u.x).all()


# --------------------------------------------------------------------------------------------
# whole sequences: shapes and intervals
# --------------------------------------------------------------------------------------------
def test_a_leading_axis_of_one_is_a_legal_batch_of_one_step_runs():
    # zs[None] has shape (1, 20, 2): T = 1 step of 20 runs (time first, as documented), not a
    # misplaced time axis; each run is one update of the prior, to a few roundings (a 2-term
    # product per entry: 4 eps relative)
    res = kalman.kalman_filter(zs[None], x, P, F, Q, H, R)
    assert res.x.shape == (1, 20, 4) and res.P.shape == (1, 20, 4, 4)
    one = kalman.update(x, P, zs, H, R)  # the 20 updates, broadcast
    np.testing.assert_allclose(res.x[0], one.x, rtol=4 * EPS, atol=4 * EPS * np.abs(one.x).max())
    np.testing.assert_allclose(res.nis[0], one.nis, rtol=16 * EPS)


def test_dt_error_gives_the_shape_not_the_values():
    with pytest.raises(ValueError, match=r"^dt must be a scalar or have shape \(20,\).*got shape \(7,\)$") as info:
        kalman.kalman_filter(zs, x, P, cv.F, cv.Q, H, R, dt=np.arange(7.0))
    assert "6." not in str(info.value)


def test_dt_from_np_diff_and_timestamps_are_accepted():
    t = np.cumsum(np.full(20, 0.5))
    ref = kalman.kalman_filter(zs, x, P, cv.F, cv.Q, H, R, dt=0.5)
    for kw in (dict(dt=np.diff(t)), dict(times=t)):
        res = kalman.kalman_filter(zs, x, P, cv.F, cv.Q, H, R, **kw)
        assert all(np.array_equal(a, b) for a, b in zip(res, ref))  # one interval: the constant form, bit for bit


def test_dt_and_times_together_are_refused_naming_both():
    with pytest.raises(ValueError, match="^dt and times exclude each other"):
        kalman.kalman_filter(zs, x, P, cv.F, cv.Q, H, R, dt=1.0, times=np.arange(20.0))


# --------------------------------------------------------------------------------------------
# the RTS smoother
# --------------------------------------------------------------------------------------------
RES = kalman.kalman_filter(zs, x, P, F, Q, H, R)


def test_smoother_with_a_zero_P_prior_names_it():
    # P_prior = 0 while P > 0 cannot come from this filter (P_prior = F P F^T + Q >= F P F^T)
    with pytest.raises(ValueError, match=r"^result\.P_prior\[19\] cannot be used by the smoother"):
        kalman.rts_smoother(RES._replace(P_prior=np.zeros_like(RES.P_prior)), F)


def test_smoother_with_nan_in_P_prior_names_it():
    with pytest.raises(ValueError, match=r"^result\.P_prior must be finite, but it contains NaN"):
        kalman.rts_smoother(RES._replace(P_prior=RES.P_prior * nan), F)


def test_smoother_of_a_known_start_without_process_noise():
    # P0 = 0, Q = 0: the system is deterministic and the state known, x_k = F^k x0, P_k = 0. The
    # smoothed state is then the filter's (G = P F^T (P^-)^+ = 0), which is the filter's last state
    # propagated back exactly: F^-(T-1-k) x_{T-1}. Rounding: x_k is k products with F (entries
    # <= 1, 2 terms), back-propagation T-1-k more: <= 4 T eps relative to max|x|.
    x0 = np.array([1.0, 0.5, -2.0, 1.5])
    Z = np.zeros((4, 4))
    res = kalman.kalman_filter(zs, x0, Z, F, Z, H, R)
    sm = kalman.rts_smoother(res, F)
    T = zs.shape[0]
    back = np.array([np.linalg.matrix_power(np.linalg.inv(F), T - 1 - k) @ res.x[-1] for k in range(T)])
    np.testing.assert_allclose(sm.x, back, rtol=0, atol=4 * T * EPS * np.abs(back).max())
    np.testing.assert_array_equal(sm.x, res.x)
    np.testing.assert_array_equal(sm.P, np.zeros_like(sm.P))
    np.testing.assert_array_equal(sm.x[-1], res.x[-1])  # the last step is the filter's
    np.testing.assert_array_equal(sm.P[-1], res.P[-1])
    # the nearby nonsingular problem P0 = d I: the smoother (Q = 0) is the MAP estimate of x0 from
    # the prior N(x0, d I) and all measurements, x0_s = (I/d + J)^-1 (x0/d + g), J = sum A_k^T R^-1 A_k,
    # g = sum A_k^T R^-1 z_k, A_k = H F^k; so |x0_s - x0| <= d |g - J x0| and
    # |x_s,k(d) - x_k| <= |F^k| d |g - J x0| (2-norms; 1.01 for the O(d^2) remainder and rounding)
    d = 1e-9
    A = [H @ np.linalg.matrix_power(F, k) for k in range(T)]
    Ri = np.linalg.inv(R)
    J = sum(a.T @ Ri @ a for a in A)
    g = sum(a.T @ Ri @ zk for a, zk in zip(A, zs))
    near = kalman.rts_smoother(kalman.kalman_filter(zs, x0, d * np.eye(4), F, Z, H, R), F)
    for k in range(T):
        bound = 1.01 * np.linalg.norm(np.linalg.matrix_power(F, k), 2) * d * np.linalg.norm(g - J @ x0)
        assert np.linalg.norm(near.x[k] - sm.x[k]) <= bound + 64 * EPS * np.abs(sm.x).max()


def test_smoother_of_a_known_start_with_rank_deficient_process_noise():
    # P0 = 0 with the discrete white-noise-acceleration Q (rank 2 of 4): the early predictions are
    # singular, the gain takes the pseudo-inverse (range condition: F P F^T lies in the range of
    # P^- = F P F^T + Q). Checks: the last step is the filter's; the smoothed covariances are PSD;
    # and the result is the limit d -> 0 of the nonsingular problem P0 = d I: the smoothed mean is
    # a smooth function of P0 near 0, so its distance to the limit shrinks in proportion to d
    # (d = 1e-6 -> 1e-8: by 100; factor 5 slack for the O(d^2) term and the conditioning 1/d of
    # the nonsingular solve, whose rounding floor is eps/d = 2e-8 of the scale).
    dw = models.ConstantVelocity(ndim=2, sigma2=1.0)
    Fd, Qd = dw.F(1.0), dw.Q(1.0)
    Z = np.zeros((4, 4))
    assert np.linalg.matrix_rank(Qd) == 2
    res = kalman.kalman_filter(zs, x, Z, Fd, Qd, H, R)
    sm = kalman.rts_smoother(res, Fd)
    assert np.isfinite(sm.x).all() and np.isfinite(sm.P).all()
    np.testing.assert_array_equal(sm.x[-1], res.x[-1])
    np.testing.assert_array_equal(sm.P[-1], res.P[-1])
    scale = np.abs(sm.x).max()
    assert np.linalg.eigvalsh(sm.P).min() >= -1e3 * 4 * EPS * np.abs(sm.P).max()
    dist = {}
    for d in (1e-6, 1e-8):
        near = kalman.rts_smoother(kalman.kalman_filter(zs, x, d * np.eye(4), Fd, Qd, H, R), Fd)
        dist[d] = np.abs(near.x - sm.x).max()
    assert dist[1e-6] <= 1e-3 * scale  # close already
    assert dist[1e-8] <= dist[1e-6] / 100 * 5 + 10 * EPS / 1e-8 * scale


def test_smoother_with_timestamps():
    t = np.arange(20.0) * 0.5
    res = kalman.kalman_filter(zs, x, P, cv.F, cv.Q, H, R, times=t)
    a, b = kalman.rts_smoother(res, cv.F, times=t), kalman.rts_smoother(res, cv.F, dt=0.5)
    assert all(np.array_equal(u, v) for u, v in zip(a, b))


# --------------------------------------------------------------------------------------------
# the user's functions in the EKF and UKF (NumPy engine)
# --------------------------------------------------------------------------------------------
def test_ekf_f_returning_nan_mid_run_names_f_and_the_step():
    # NaN once the first position exceeds 5 (step 4's estimate is about 5.1 with this data)
    fnan = lambda s: s @ F.T + np.where(s[..., :1] > 5, nan, 0.0)  # noqa: E731
    with pytest.raises(ValueError, match=r"^f returned NaN at step \d+ \(called on an input of shape \(4,\)\)") as info:
        ekf.extended_kalman_filter(zs, x, P, fnan, lambda s: F, Q, H, None, R)
    k = int(re.search(r"step (\d+)", str(info.value)).group(1))
    ok = ekf.extended_kalman_filter(zs[:k + 1], x, P, f, lambda s: F, Q, H, None, R)  # the same run, up to k
    assert ok.x[k, 0] > 5 and (ok.x[:k, 0] <= 5).all()  # step k is the first where f is NaN


def test_ekf_f_with_sqrt_of_negative_names_f_not_x():
    with np.errstate(invalid="ignore"):
        with pytest.raises(ValueError, match=r"^f returned NaN at step 0"):
            ekf.extended_kalman_filter(zs, x, P, lambda s: np.sqrt(s - 5.0), Fj, Q, h, Hj, R)


def test_ekf_h_with_log_of_zero_names_h():
    with np.errstate(divide="ignore"):
        with pytest.raises(ValueError, match=r"^h returned inf at step 0"):
            ekf.extended_kalman_filter(zs, x, P, f, Fj, Q, lambda s: np.log(s[..., [0, 2]]), Hj, R)


def test_ekf_jacobians_returning_nan_are_named():
    bad = lambda s: np.full(s.shape[:-1] + (4, 4), nan)  # noqa: E731
    with pytest.raises(ValueError, match=r"^F_jac returned NaN at step 0"):
        ekf.extended_kalman_filter(zs, x, P, f, bad, Q, h, Hj, R)
    with pytest.raises(ValueError, match=r"^H_jac returned NaN at step 3"):
        ekf.extended_kalman_filter(zs, x, P, f, Fj, Q, h,
                                   lambda s: np.where(s[..., :1, None] > 2.5, nan, Hj(s)), R)


def test_ukf_f_returning_nan_mid_run_names_f():
    with np.errstate(invalid="ignore"):
        with pytest.raises(ValueError, match=r"^f returned NaN at step 0 \(called on an input of shape \(9, 4\)\)"):
            ukf.unscented_kalman_filter(zs, x, P, lambda s: np.sqrt(s - 5.0), Q, h, R)


def test_ukf_h_returning_nan_names_h():
    with pytest.raises(ValueError, match=r"^h returned NaN at step 0"):
        ukf.unscented_kalman_filter(zs, x, P, f, Q, lambda s: h(s) * nan, R)


def test_ukf_accepts_a_known_start():
    # P0 = 0 (positive semi-definite): the sigma points collapse on x0 at step 0, then the UKF on a
    # linear model is the Kalman filter. The unscented moments of a linear map are exact; they
    # differ from the KF's products only by rounding in sums of 2n + 1 = 9 weighted points with
    # weights 1/8: 1e3 eps of the scale covers them over 20 steps.
    Z = np.zeros((4, 4))
    res = ukf.unscented_kalman_filter(zs, x, Z, f, Q, h, R)
    ref = kalman.kalman_filter(zs, x, Z, F, Q, H, R)
    np.testing.assert_allclose(res.x, ref.x, rtol=0, atol=1e3 * EPS * np.abs(ref.x).max())
    np.testing.assert_allclose(res.P, ref.P, rtol=0, atol=1e3 * EPS * np.abs(ref.P).max())
    tr = ukf.unscented_transform(lambda s: s, x, Z)
    np.testing.assert_array_equal(tr.sigma.X, np.zeros((9, 4)))  # every point on the known state


def test_sigma_points_of_a_positive_definite_P_are_the_cholesky_ones():
    # the fallback leaves a positive definite P alone: the points are x +- columns of chol(cP)
    sp = ukf.MerweScaledSigmaPoints()(x, P)
    L = np.linalg.cholesky(4.0 * P)
    np.testing.assert_array_equal(sp.X[1:5], L.T)
    with pytest.raises(ValueError, match="^P must be positive semi-definite"):
        ukf.MerweScaledSigmaPoints()(x, np.diag([1.0, 1.0, 1.0, -1.0]))


def test_singular_priors_in_per_run_covariances_smooth_as_one_run():
    # the same known-start problem with a per-run R (3 runs, so per-run covariances: the batched
    # path of the gain) gives each run the single run's smoother; the same products per run, but
    # batched LAPACK/BLAS calls may sum in another order: 1e3 eps of the scale
    dw = models.ConstantVelocity(ndim=2, sigma2=1.0)
    Fd, Qd, Z = dw.F(1.0), dw.Q(1.0), np.zeros((4, 4))
    one = kalman.rts_smoother(kalman.kalman_filter(zs, x, Z, Fd, Qd, H, R), Fd)
    runs = kalman.rts_smoother(kalman.kalman_filter(np.repeat(zs[:, None], 3, 1), x, Z, Fd, Qd, H,
                                                    np.broadcast_to(R, (3, 2, 2))), Fd)
    for i in range(3):
        np.testing.assert_allclose(runs.x[:, i], one.x, rtol=0, atol=1e3 * EPS * np.abs(one.x).max())
        np.testing.assert_allclose(runs.P[:, i], one.P, rtol=0, atol=1e3 * EPS * np.abs(one.P).max())

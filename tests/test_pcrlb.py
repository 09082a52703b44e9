"""Tests of the Monte Carlo consistency test and the posterior Cramér-Rao lower bound in
kftrack.metrics: the PCRLB of a linear-Gaussian model equals the Kalman covariance (also with
a singular Q and time-varying H); the linear KF's NEES and NIS inside chi-square bounds on
random seeded systems, a mistuned filter outside; the bound below the EKF's error on radar;
bad input."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from kftrack import ekf, kalman, metrics
from kftrack.kernels import mv as _mv
from kftrack.sensors.radar import RangeBearing


def random_spd(rng, n, scale=1.0):
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T + n * np.eye(n))


def cv2d(dt, q):
    Fa = np.array([[1.0, dt], [0.0, 1.0]])
    Qa = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    return np.kron(np.eye(2), Fa), np.kron(np.eye(2), Qa)


def test_pcrlb_equals_kalman_covariance_linear_gaussian():
    # the reference figure: 2-D CV, T = 2, q = 0.5, R = 25 I, 20 steps, max |J^-1 - P_KF| ~ 4e-14
    F, Q = cv2d(2.0, 0.5)
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    R = 25.0 * np.eye(2)
    P0 = np.diag([100.0, 25.0, 100.0, 25.0])
    zs = np.zeros((20, 2))  # covariances do not depend on the data
    kf = kalman.kalman_filter(zs, np.zeros(4), P0, F, Q, H, R)
    b = metrics.pcrlb(P0, F, Q, H, R, steps=20)
    assert np.max(np.abs(b.P - kf.P)) < 1e-12 * np.max(np.abs(kf.P))
    assert np.max(np.abs(b.P_prior - kf.P_prior)) < 1e-12 * np.max(np.abs(kf.P_prior))
    assert np.allclose(b.J @ b.P, np.eye(4), atol=1e-12)


def test_pcrlb_with_singular_q_and_time_varying_h():
    rng = np.random.default_rng(3)
    dt, sigma2 = 1.0, 0.3
    Fa = np.array([[1.0, dt], [0.0, 1.0]])
    Ga = np.array([[dt**2 / 2], [dt]])
    F, Q = np.kron(np.eye(2), Fa), np.kron(np.eye(2), sigma2 * Ga @ Ga.T)  # DWNA: rank 2 of 4
    assert np.linalg.matrix_rank(Q) == 2
    T = 15
    Hs = rng.normal(size=(T, 2, 4))
    R = random_spd(rng, 2)
    P0 = random_spd(rng, 4)
    b = metrics.pcrlb(P0, F, Q, Hs, R)
    P = P0
    for k in range(T):
        u = kalman.update(np.zeros(4), P, np.zeros(2), Hs[k], R)
        assert np.allclose(b.P[k], u.P, rtol=1e-10, atol=1e-12 * np.max(np.abs(u.P)))
        _, P = kalman.predict(np.zeros(4), u.P, F, Q)


def test_pcrlb_average_runs_shape_and_value():
    rng = np.random.default_rng(4)
    H = rng.normal(size=(5, 3, 1, 2))  # T=5 steps, N=3 truths
    R = np.eye(1)
    b = metrics.pcrlb(np.eye(2), np.eye(2), 0.1 * np.eye(2), H, R, average_runs=True)
    assert b.P.shape == (5, 2, 2)
    info = np.mean(np.swapaxes(H[0], -1, -2) @ H[0], axis=0)
    assert np.allclose(b.J[0], np.eye(2) + info, rtol=1e-13)


@pytest.mark.parametrize("seed", [10, 11, 12, 13])
def test_linear_kf_nees_and_nis_inside_chi_square_bounds(seed):
    rng = np.random.default_rng(seed)
    n, m, T, N = 4, 2, 40, 300
    F = np.linalg.qr(rng.normal(size=(n, n)))[0] * 0.98  # stable
    Q, H, R = random_spd(rng, n, 0.05), rng.normal(size=(m, n)), random_spd(rng, m)
    x0, P0 = rng.normal(size=n), random_spd(rng, n)
    f, h = (lambda x: _mv(F, x)), (lambda x: _mv(H, x))
    truth, zs = ekf.simulate_additive_gaussian(f, h, x0, P0, Q, R, T, rng, runs=N)
    kf = kalman.kalman_filter(zs, x0, P0, F, Q, H, R)
    ne = metrics.nees(truth, kf.x, kf.P)
    # one step (the last): N runs, independent, average ~ chi2(N n)/N
    lo, hi = metrics.chi2_bounds(n, N, 0.999)
    assert lo < ne[-1].mean() < hi
    # NIS is white in time for a consistent filter: the time average has the N T m bound
    c = metrics.consistency(kf.nis, m, confidence=0.999)
    assert c.time_bounds[0] < c.time_average < c.time_bounds[1]
    assert c.runs == N and c.steps == T
    # a filter that believes Q is 100 times smaller is caught by the same test
    bad = kalman.kalman_filter(zs, x0, P0, F, Q / 100, H, R)
    cb = metrics.consistency(bad.nis, m, confidence=0.999)
    assert not cb.time_bounds[0] < cb.time_average < cb.time_bounds[1]


def test_consistency_fields_and_missing_rows():
    rng = np.random.default_rng(0)
    v = rng.chisquare(2, size=(30, 50))
    v[4] = np.nan
    c = metrics.consistency(v, 2)
    assert np.isnan(c.mean[4]) and c.steps == 29 and c.runs == 50
    assert c.bounds == metrics.chi2_bounds(2, 50)
    assert c.time_bounds == metrics.chi2_bounds(2, 50 * 29)
    assert np.isclose(c.time_average, np.nanmean(v))
    kept = np.delete(c.mean, 4)
    assert c.inside == np.mean((kept >= c.bounds[0]) & (kept <= c.bounds[1]))


def test_ekf_error_on_radar_is_above_the_pcrlb():
    """For a nonlinear measurement the bound holds but is not reached: the EKF's Monte Carlo
    mean squared error per position component is not below the bound (one-sided chi-square)."""
    rng = np.random.default_rng(8)
    dt, T, N = 1.0, 30, 400
    F, Q = cv2d(dt, 0.1)
    radar = RangeBearing(sigmas=(5.0, 0.02))
    x0 = np.array([300.0, -10.0, 400.0, 5.0])
    P0 = np.diag([100.0, 4.0, 100.0, 4.0])
    f = lambda x: _mv(F, x)
    truth, zs = ekf.simulate_additive_gaussian(f, radar.h, x0, P0, Q, radar.R, T, rng, runs=N,
                                               angle_components=radar.angle_components)
    assert np.all(np.abs(zs[..., 1]) <= np.pi)
    res = ekf.extended_kalman_filter(zs, x0, P0, f, lambda x: np.broadcast_to(F, x.shape[:-1] + (4, 4)), Q,
                                     radar.h, radar.jacobian, radar.R, radar.angle_components)
    b = metrics.pcrlb(P0, F, Q, radar.jacobian(truth), radar.R, average_runs=True)
    mse = np.mean((res.x[-1] - truth[-1]) ** 2, axis=0)
    bound = np.diag(b.P[-1])
    # if the true variance were the bound, N * mse / bound ~ chi2(N); require it not be far below
    assert np.all(N * mse / bound > stats.chi2.ppf(0.001, N))


def test_bad_input_names_the_argument():
    with pytest.raises(ValueError, match="steps"):
        metrics.pcrlb(np.eye(2), np.eye(2), np.eye(2), np.eye(2), np.eye(2))
    with pytest.raises(ValueError, match="P0"):
        metrics.pcrlb(np.zeros((2, 2)), np.eye(2), np.eye(2), np.eye(2), np.eye(2), steps=3)
    with pytest.raises(ValueError, match=r"^H must"):
        metrics.pcrlb(np.eye(2), np.eye(2), np.eye(2), np.zeros((4, 1, 2)), np.eye(1), steps=3)
    with pytest.raises(ValueError, match="average_runs"):
        metrics.pcrlb(np.eye(2), np.eye(2), np.eye(2), np.zeros((3, 1, 2)), np.eye(1), average_runs=True)
    with pytest.raises(ValueError, match="values"):
        metrics.consistency(np.ones(5), 2)
    with pytest.raises(ValueError, match="partly NaN"):
        metrics.consistency(np.array([[1.0, np.nan], [1.0, 1.0]]), 2)
    with pytest.raises(ValueError, match="dof"):
        metrics.consistency(np.ones((3, 2)), 0)


def test_plot_chi2_band_draws_the_mean_and_the_band():
    import matplotlib.pyplot as plt

    from kftrack.plotting import plot_chi2_band

    c = metrics.consistency(np.random.default_rng(1).chisquare(2, size=(10, 30)), 2)
    fig, ax = plt.subplots()
    line = plot_chi2_band(ax, np.arange(10), c.mean, c.bounds, label="NIS")
    assert np.array_equal(line.get_ydata(), c.mean)
    (band,) = ax.patches
    assert np.isclose(band.get_y(), c.bounds[0])  # axhspan: a rectangle from lower to upper
    assert np.isclose(band.get_y() + band.get_height(), c.bounds[1])
    plt.close(fig)


def test_pcrlb_riccati_form_equals_general_information_recursion_for_linear_dynamics():
    # Tichavsky et al. (1998): J_{k+1} = D22 - D21 (J_k + D11)^-1 D12 with D11 = F^T Q^-1 F,
    # D12 = -F^T Q^-1, D22 = Q^-1 + H^T R^-1 H; for a state-independent F it is the Riccati form.
    rng = np.random.default_rng(8)
    n, m, T = 4, 2, 12
    F = rng.normal(size=(n, n))
    Q, R, P0 = random_spd(rng, n, 0.3), random_spd(rng, m), random_spd(rng, n)
    Hs = rng.normal(size=(T, m, n))
    b = metrics.pcrlb(P0, F, Q, Hs, R)
    Qi = np.linalg.inv(Q)
    J = np.linalg.inv(P0) + Hs[0].T @ np.linalg.solve(R, Hs[0])
    for k in range(T - 1):
        D11, D12 = F.T @ Qi @ F, -F.T @ Qi
        D22 = Qi + Hs[k + 1].T @ np.linalg.solve(R, Hs[k + 1])
        assert np.linalg.cond(J + D11) < 1e4  # the premise of the tolerance below
        J = D22 - D12.T @ np.linalg.solve(J + D11, D12)
        # relative agreement to round-off: a few products of n x n matrices with condition
        # numbers below 1e4 here, so 1e4 * n * eps ~ 1e-11 bounds the difference
        assert np.max(np.abs(J - b.J[k + 1])) < 1e4 * n * np.finfo(float).eps * np.max(np.abs(J))

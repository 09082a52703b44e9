"""The named steps of the chapter-18 recipe's loop (``kftrack.aircraft._run``), each on its own:
restart (``_track_start``), hold (``_held_copy``, ``_spike_ahead``), the resampler's frame
(``_interpolated``, ``_p_interpolated``, the interval window), predict over a segment (``_predict_row``),
the gate (``_too_fast``, ``_held_axis``, ``_innovation``, ``_nis``, ``_gate``), the IMM step's update
(``_imm_update``) and the score (``_score``, ``_log_rmse``). ``tests/test_aircraft.py`` checks the loop
they make up."""
from __future__ import annotations

import math

import numpy as np

from kftrack import aircraft as A


def test_track_start_is_the_two_point_start():
    mu0 = np.full(4, 0.25)
    z0, z1, dt = np.array([0.0, 0.0]), np.array([100.0, 50.0]), 5.0
    mu, xs, Ps = A._track_start(z0, z1, dt, mu0, 200.0, 1.0, 6)
    x, P = A.two_point_init(z0, z1, dt, 300.0)          # a track's start: white r0 + 100 on both positions
    assert mu is mu0 and xs.shape == (4, 4) and Ps.shape == (4, 4, 4)
    assert np.array_equal(xs, np.tile(x, (4, 1))) and np.array_equal(Ps, np.tile(P, (4, 1, 1)))
    # a restart inside a track with no lag term: R = (r0 + r_q) I, the two-point start with r = r0 + r_q
    # (the same divisions: equal to round-off, 1e-15 relative)
    rq = (111_320.0 * 1e-6) ** 2 / 12.0
    _, xs2, Ps2 = A._track_start(z0, z1, dt, mu0, 200.0, 0.0, 6, delta=5.0)
    _, P2 = A.two_point_init(z0, z1, dt, 200.0 + rq)
    assert np.allclose(Ps2[0], P2, rtol=1e-15, atol=0) and np.array_equal(xs2, xs)
    # with the lag term the along-track variance grows by c Delta^2 |v|^2 / 12 (v = (20, 10) m/s)
    _, _, Ps3 = A._track_start(z0, z1, dt, mu0, 200.0, 1.0, 6, delta=5.0)
    v = np.array([20.0, 10.0])
    u = v / np.linalg.norm(v)
    along = u @ Ps3[0][np.ix_([0, 2], [0, 2])] @ u
    assert abs(along - (200.0 + rq + 25.0 * 500.0 / 12.0)) <= 1e-9 * along


def test_held_copy_is_nearer_held_than_flown():
    spike = (100.0, 0.0, 0.0, 52.0, 4.0)                 # E, N, t, lat, lon of the spike
    zf, v = np.array([0.0, 0.0]), np.array([10.0, 0.0])  # the filter's prediction, velocity 10 m/s east
    # 5 m from the spike after 2 s: less than half of the 20 m the aircraft would have flown
    assert A._held_copy(np.array([95.0, 0.0]), zf, spike, v, 2.0, 51.0, 3.0, False)
    # as far from the spike as from the prediction: not nearer the spike
    assert not A._held_copy(np.array([50.0, 0.0]), zf, spike, v, 2.0, 51.0, 3.0, False)
    # 10 m after 1 s (more than half of 10 m) is "flown", unless it repeats a coordinate of the spike
    # exactly, which counts only when no undo is pending
    assert not A._held_copy(np.array([90.0, 0.0]), zf, spike, v, 1.0, 51.0, 3.0, False)
    assert A._held_copy(np.array([90.0, 0.0]), zf, spike, v, 1.0, 52.0, 3.0, False)
    assert not A._held_copy(np.array([90.0, 0.0]), zf, spike, v, 1.0, 52.0, 3.0, True)


def test_interpolated_row_is_on_the_segment_at_its_time():
    tl = [0.0, 5.0, 15.0]
    la, lo = [52.0, 52.001, 52.003], [4.0, 4.002, 4.006]  # row 1 at a third of the segment, at a third of the time
    assert A._interpolated(la, lo, tl, 0, 1, 2) == 1
    la_off = [52.0, 52.001 + 1e-8, 52.003]               # 1e-8 deg off (1 mm): a recorded fix
    assert A._interpolated(la_off, lo, tl, 0, 1, 2) == 0
    assert A._interpolated(la, lo, [0.0, 7.5, 15.0], 0, 1, 2) == 0   # on the line, not at the time-proportional point


def test_imm_update_is_the_kalman_update_per_mode():
    rng = np.random.default_rng(18)
    r = 3
    L = rng.standard_normal((r, 4, 4))
    Pp = L @ L.transpose(0, 2, 1) + 4 * np.eye(4)
    xp = rng.standard_normal((r, 4))
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    R = np.array([[2.0, 0.3], [0.3, 1.5]])
    S = H @ Pp @ H.T + R
    z = np.array([0.4, -0.7])
    y = z - xp[:, [0, 2]]
    for infl in (1.0, 4.0):
        xs, Ps = A._imm_update(xp, Pp, S[:, 0, 0], S[:, 0, 1], S[:, 1, 1], np.linalg.det(S), y[:, 0], y[:, 1], infl)
        for j in range(r):
            K = Pp[j] @ H.T @ np.linalg.inv(infl * S[j])
            # 4x4 products of O(10) numbers: round-off ~1e-14; 1e-12 is a wide bound
            assert np.allclose(xs[j], xp[j] + K @ y[j], rtol=0, atol=1e-12)
            assert np.allclose(Ps[j], Pp[j] - K @ H @ Pp[j], rtol=0, atol=1e-12)
            assert np.array_equal(Ps[j], Ps[j].T)


def _modes(r=3, seed=26):
    """A random IMM prediction: probabilities c (r,), predicted states xp (r, 4), covariances Pp (r, 4, 4)."""
    rng = np.random.default_rng(seed)
    L = rng.standard_normal((r, 4, 4))
    c = rng.dirichlet(np.ones(r))
    return c, 10.0 * rng.standard_normal((r, 4)), L @ L.transpose(0, 2, 1) + 4 * np.eye(4)


def test_predict_row_mixes_filter_and_segment():
    rng = np.random.default_rng(7)
    r = 4
    mu = rng.dirichlet(np.ones(r))
    xs = 10.0 * rng.standard_normal((r, 4))
    Ps = np.tile(np.eye(4), (r, 1, 1))
    modes = A._Modes(A.Q_MODES, A.SOJOURN_S, A.OMEGA_MODES)
    F, Q, Pi = modes(4.0)
    c, xp, _ = A._imm_predict(mu, xs, Ps, F, Q, Pi)
    zkf = c @ xp[:, [0, 2]]                               # the IMM's predicted position, sum_j c_j H x^-_j
    pred, zf = A._predict_row(mu, xs, F, Pi)
    # the same products in another order: round-off of O(1e-15) relative on positions of O(100) m
    assert np.allclose(zf, zkf, rtol=0, atol=1e-10) and np.array_equal(pred, zf)
    z2, z1, a = np.array([0.0, 0.0]), np.array([100.0, 40.0]), 0.5     # half the last segment ahead
    zl = np.array([150.0, 60.0])
    assert np.array_equal(A._predict_row(mu, xs, F, Pi, (z2, z1, a, 0.0))[0], zf)
    assert np.allclose(A._predict_row(mu, xs, F, Pi, (z2, z1, a, 1.0))[0], zl, rtol=0, atol=1e-12)
    assert np.allclose(A._predict_row(mu, xs, F, Pi, (z2, z1, a, 0.25))[0], 0.25 * zl + 0.75 * zf,
                       rtol=0, atol=1e-12)


def test_p_interpolated_is_the_beta_posterior_mean():
    assert A._p_interpolated({}, (0, 6)) == 0.5                  # uniform prior: no row seen
    assert A._p_interpolated({(0, 6): [4.0, 2.0]}, (0, 6)) == 2.0 / 6.0
    assert A._p_interpolated({(0, 6): [4.0, 2.0]}, (1, 6)) == 0.5   # another history: its own counts


def test_too_fast_is_the_speed_limit():
    z0 = np.array([0.0, 0.0])
    assert A._too_fast(np.array([1200.0, 1600.0 + 1.0]), z0, 5.0)       # 2000.6 m in 5 s > 400 m/s
    assert not A._too_fast(np.array([1200.0, 1600.0 - 1.0]), z0, 5.0)   # 1999.4 m in 5 s < 400 m/s


def test_spike_ahead_along_the_velocity():
    spike = (100.0, 50.0, 3.0, 52.0, 4.0)
    assert A._spike_ahead(spike, np.array([0.0, 0.0]), np.array([10.0, 0.0]))       # ahead, flying east
    assert not A._spike_ahead(spike, np.array([0.0, 0.0]), np.array([-10.0, 0.0]))  # behind, flying west
    assert not A._spike_ahead(spike, np.array([0.0, 0.0]), np.array([5.0, -10.0]))  # abeam: (100, 50).v = 0


def test_held_axis_names_the_repeated_coordinate():
    last = (52.0, 4.0)
    assert A._held_axis(52.1, 4.1, last) == 0
    assert A._held_axis(52.1, 4.0, last) == 1          # longitude held: east not measured
    assert A._held_axis(52.0, 4.1, last) == 2          # latitude held: north not measured


def test_innovation_is_hph_plus_the_lag_covariance():
    c, xp, Pp = _modes()
    zk = np.array([3.0, -2.0])
    cl, r0 = 2.5, 200.0
    v = c @ xp[:, [1, 3]]
    R = cl * np.outer(v, v) + r0 * np.eye(2)
    S00, S01, S11, det, y0, y1 = A._innovation(xp, Pp, c, zk, cl, r0, 0)
    S = Pp[:, [0, 2]][:, :, [0, 2]] + R
    # sums of a few O(100) numbers: round-off ~1e-13; 1e-9 is a wide bound
    assert np.allclose(S00, S[:, 0, 0], rtol=0, atol=1e-9) and np.allclose(S01, S[:, 0, 1], rtol=0, atol=1e-9)
    assert np.allclose(S11, S[:, 1, 1], rtol=0, atol=1e-9)
    assert np.allclose(det, np.linalg.det(S), rtol=1e-12, atol=0)
    assert np.array_equal(y0, zk[0] - xp[:, 0]) and np.array_equal(y1, zk[1] - xp[:, 2])
    H00, _, H11, _, _, _ = A._innovation(xp, Pp, c, zk, cl, r0, 1)     # east held: not measured
    assert np.array_equal(H00, S00 + 1e12) and np.array_equal(H11, S11)
    H00, _, H11, _, _, _ = A._innovation(xp, Pp, c, zk, cl, r0, 2)     # north held
    assert np.array_equal(H00, S00) and np.array_equal(H11, S11 + 1e12)


def test_nis_of_the_moment_matched_density():
    c, xp, Pp = _modes()
    zk = np.array([3.0, -2.0])
    S00, S01, S11, _, _, _ = A._innovation(xp, Pp, c, zk, 1.0, 50.0, 0)
    S = np.stack([np.stack([S00, S01], -1), np.stack([S01, S11], -1)], -2)
    zb = c @ xp[:, [0, 2]]
    d = xp[:, [0, 2]] - zb
    T = np.einsum("j,jab->ab", c, S + d[:, :, None] * d[:, None, :])
    e = zk - zb
    # a 2x2 solve of O(100) numbers: round-off ~1e-14 relative
    assert math.isclose(A._nis(c, xp, S00, S01, S11, zk), e @ np.linalg.solve(T, e), rel_tol=1e-12)


def test_gate_inflates_beyond_the_chi2_quantile():
    gamma = A._gamma(1e-4)                               # 18.42 (two coordinates), 15.14 (one)
    assert A._gate(18.0, gamma, 0) == (False, 1.0)
    gated, infl = A._gate(36.84, gamma, 0)
    assert gated and infl == 36.84 / gamma[2]
    assert A._gate(16.0, gamma, 1) == (True, 16.0 / gamma[1])   # one measured coordinate: the 1-dof gate


def test_score_is_the_mixture_density():
    from scipy.stats import multivariate_normal, norm
    c, xp, Pp = _modes()
    zk = np.array([3.0, -2.0])
    inn = A._innovation(xp, Pp, c, zk, 1.0, 50.0, 0)
    S = np.stack([np.stack([inn[0], inn[1]], -1), np.stack([inn[1], inn[2]], -1)], -2)
    y = np.stack([inn[4], inn[5]], -1)
    dens = np.array([c[j] * multivariate_normal(np.zeros(2), S[j]).pdf(y[j]) for j in range(c.size)])
    ell, mu = A._score(c, *inn, 0)
    # log-sum-exp against scipy's densities: round-off ~1e-14 relative
    assert math.isclose(ell, math.log(dens.sum()), rel_tol=1e-12)
    assert np.allclose(mu, dens / dens.sum(), rtol=1e-12, atol=0)
    # north held (1e12 m² added): the density of east alone; the neglected terms,
    # (S11 + y1² + S01²/S00) / (2e12), are below 1e-9 here (S and y of O(100); 5.5e-11 measured)
    inn = A._innovation(xp, Pp, c, zk, 1.0, 50.0, 2)
    ell, _ = A._score(c, *inn, 2)
    marg = sum(c[j] * norm(0.0, math.sqrt(inn[0][j])).pdf(inn[4][j]) for j in range(c.size))
    assert abs(ell - math.log(marg)) <= 1e-9


def test_log_rmse_of_the_scored_rows():
    enu = np.zeros((4, 2))
    pred = np.array([[np.nan, np.nan], [3.0, 4.0], [0.0, 5.0], [100.0, 0.0]])
    m = np.array([False, True, True, False])             # errors of 5 m on the two scored rows
    assert math.isclose(A._log_rmse(pred, enu, m), math.log(5.0), rel_tol=1e-15)


def test_interval_is_the_median_of_the_window():
    s = A._Loop(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros((1, 2)), np.ones(1, bool), 4, 1.0, 200.0)
    deltas = [s.interval(dt) for dt in [1.0] * A.DT_WINDOW + [5.0] * (A.DT_WINDOW // 2 + 1)]
    assert deltas[A.DT_WINDOW - 1] == 1.0
    assert deltas[-2] == 1.0 and deltas[-1] == 5.0      # the median turns when 5 s fills half the window
    assert len(s.dts) == len(s.dts_sorted) == A.DT_WINDOW

"""Tests of kftrack.gpsfusion (speed-heading model, stacked fusion, lane metric) and
kftrack.gpstrack (the synthetic athletics-track world and its committed NMEA logs)."""
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from kftrack import gpsfusion as gf
from kftrack import gpstrack as gt
from kftrack.kalman import predict, update


# --- the thesis's model -----------------------------------------------------------------------

@given(h=st.floats(-4, 4), v=st.floats(0, 10), dt=st.floats(0.1, 2))
def test_jacobian_against_central_differences(h, v, dt):
    x = np.array([3.0, -2.0, v, h])

    def f(s):
        return gf.thesis_transition(s[3], dt) @ s

    eps = 1e-6
    J = np.column_stack([(f(x + eps * e) - f(x - eps * e)) / (2 * eps) for e in np.eye(4)])
    np.testing.assert_allclose(gf.speed_heading_jacobian(x, dt), J, atol=1e-6)
    # the thesis's A_k differs from the Jacobian exactly in the heading column
    D = gf.speed_heading_jacobian(x, dt) - gf.thesis_transition(h, dt)
    np.testing.assert_allclose(D[:, [0, 1, 2]], 0.0)
    np.testing.assert_allclose(D[:2, 3], [-dt * v * np.sin(h), dt * v * np.cos(h)], atol=1e-12)


@given(h=st.floats(-4, 4), dt=st.floats(0.1, 3), sa=st.floats(0.01, 5), sw=st.floats(0.01, 5))
def test_process_noise_entries_symmetric_rank_two(h, dt, sa, sw):
    Q = gf.thesis_process_noise(h, dt, sa, sw)
    c, s = np.cos(h), np.sin(h)
    expected = np.array([
        [sa * dt**4 * c * c / 4, sa * dt**4 * c * s / 4, sa * dt**3 * c / 2, 0],
        [sa * dt**4 * c * s / 4, sa * dt**4 * s * s / 4, sa * dt**3 * s / 2, 0],
        [sa * dt**3 * c / 2, sa * dt**3 * s / 2, sa * dt**2, 0],
        [0, 0, 0, sw * dt**2]])
    np.testing.assert_allclose(Q, expected, rtol=1e-12, atol=1e-14)
    assert np.linalg.matrix_rank(Q, tol=1e-9 * np.abs(Q).max()) == 2
    assert np.linalg.eigvalsh(Q).min() > -1e-12 * np.abs(Q).max()


def test_quadrant_formulas_q1_q3_right_q2_q4_wrong():
    chi = np.array([30.0, 120.0, 210.0, 300.0])
    a13, a23 = gf.thesis_quadrant_terms(chi)
    right13, right23 = np.sin(np.deg2rad(chi)), np.cos(np.deg2rad(chi))
    np.testing.assert_allclose(a13[[0, 2]], right13[[0, 2]], atol=1e-12)
    np.testing.assert_allclose(a23[[0, 2]], right23[[0, 2]], atol=1e-12)
    np.testing.assert_allclose([a13[1], a23[1]], [-right13[1], -right23[1]], atol=1e-12)  # reversed
    np.testing.assert_allclose([a13[3], a23[3]], [right13[3], -right23[3]], atol=1e-12)   # north flipped


# --- the filter ---------------------------------------------------------------------------------

def test_filter_one_step_equals_kalman_update_predict():
    rng = np.random.default_rng(0)
    z = rng.normal(size=(1, 3, 4)) + np.array([0, 0, 1.5, 0.3])
    x0, P0 = np.array([0.1, -0.2, 1.4, 0.2]), 10 * np.eye(4)
    R = 0.05 * np.eye(4)
    res = gf.speed_heading_filter(z, x0, P0, np.eye(4), R)
    upd = update(x0, P0, z[0], np.eye(4), R)
    np.testing.assert_allclose(res.x[0], upd.x, atol=1e-12)
    np.testing.assert_allclose(res.P[0], np.broadcast_to(upd.P, (3, 4, 4)), atol=1e-12)
    np.testing.assert_allclose(res.K, np.broadcast_to(upd.K, (3, 4, 4)), atol=1e-12)


def test_two_identical_receivers_with_double_noise_equal_one():
    rng = np.random.default_rng(1)
    T = 40
    truth = gt.lap_truth(gt.INNER_RADIUS)[:T]
    z = truth + rng.normal(scale=[1, 1, 0.1, 0.05], size=(T, 4))
    one = gf.speed_heading_filter(z, z[0], 10 * np.eye(4), np.eye(4), 0.05 * np.eye(4), jacobian=True)
    two = gf.speed_heading_filter(np.concatenate([z, z], -1), z[0], 10 * np.eye(4), np.eye(4), 0.1 * np.eye(8),
                                  jacobian=True)
    np.testing.assert_allclose(two.x, one.x, atol=1e-9)
    np.testing.assert_allclose(two.P, one.P, atol=1e-9)


def test_thesis_gain_matches_scalar_riccati_and_fusion_halves_it():
    truth = gt.lap_truth(gt.INNER_RADIUS)
    z = np.repeat(truth[:, None, :], 2, axis=1)[:, None, :, :]  # (T, 1, r=2, 4)
    single = gf.speed_heading_filter(z[:, :, 0], truth[0], 10 * np.eye(4), np.eye(4), 0.05 * np.eye(4))
    fused = gf.speed_heading_filter(z.reshape(len(truth), 1, 8), truth[0], 10 * np.eye(4), np.eye(4),
                                    0.05 * np.eye(8))
    p = (1 + np.sqrt(1 + 4 * 0.05)) / 2           # scalar Riccati p^2 - p - r = 0 for A = 1, q = 1
    assert single.K[0, 3, 3] == pytest.approx(p / (p + 0.05), abs=1e-6)   # heading: decoupled channel
    assert np.diag(single.K[0])[:2] == pytest.approx(0.955, abs=0.01)
    K = fused.K[0]
    np.testing.assert_allclose(K[:, :4], K[:, 4:], atol=1e-12)          # equal weights: an average
    p2 = (1 + np.sqrt(1 + 4 * 0.025)) / 2
    assert K[3, 3] == pytest.approx(0.5 * p2 / (p2 + 0.025), abs=1e-6)


def test_heading_wraps_across_pi():
    truth = gt.lap_truth(gt.INNER_RADIUS)  # heading passes through +-pi on the north straight
    res = gf.speed_heading_filter(truth, truth[0], np.eye(4), 0.01 * np.eye(4), 0.05 * np.eye(4), jacobian=True)
    err = (res.x[:, 3] - truth[:, 3] + np.pi) % (2 * np.pi) - np.pi
    assert np.max(np.abs(err)) < 0.2
    assert np.all(np.abs(res.x[:, 3]) <= np.pi)


def test_filter_bad_input():
    with pytest.raises(ValueError, match="zs"):
        gf.speed_heading_filter(np.zeros((5, 6)), np.zeros(4), np.eye(4), np.eye(4), np.eye(6))
    with pytest.raises(ValueError, match=r"^R must"):
        gf.speed_heading_filter(np.zeros((5, 8)), np.zeros(4), np.eye(4), np.eye(4), np.eye(4))
    with pytest.raises(ValueError, match="x0"):
        gf.speed_heading_filter(np.zeros((5, 4)), np.zeros(3), np.eye(4), np.eye(4), np.eye(4))
    with pytest.raises(ValueError, match="sigma2_a"):
        gf.thesis_process_noise(0.0, 1.0, -1.0, 1.0)


# --- fusion weights -------------------------------------------------------------------------------

@given(s1=st.floats(0.1, 5), s2=st.floats(0.1, 5), rho=st.floats(-0.9, 0.9))
def test_fusion_weights_minimum_variance(s1, s2, rho):
    C = np.array([[s1**2, rho * s1 * s2], [rho * s1 * s2, s2**2]])
    w = gf.fusion_weights(C)
    assert w.sum() == pytest.approx(1.0)
    best = w @ C @ w
    for a in np.linspace(-1, 2, 31):
        v = np.array([a, 1 - a])
        assert best <= v @ C @ v + 1e-12
    if rho == 0:
        assert w[0] == pytest.approx(s2**2 / (s1**2 + s2**2))


# --- lane metric and pairing (C9) -------------------------------------------------------------------

def test_lane_metric_on_true_laps():
    inner = gt.lap_truth(gt.INNER_RADIUS)[:, :2]
    outer = gt.lap_truth(gt.INNER_RADIUS + gt.LANE_SEPARATION)[:, :2]
    d_poly = gf.lane_distances(inner, outer, "polyline")
    d_near = gf.lane_distances(inner, outer, "nearest")
    d_index = gf.lane_distances(inner, outer, "index")
    sagitta = 1.5**2 / (8 * gt.INNER_RADIUS)
    assert np.all(d_poly >= 7.32 - 1e-9) and np.all(d_poly <= 7.32 + sagitta + 1e-9)
    # nearest vertex at most half a step (0.75 m of inner arc) away: on the bends
    # d^2 = 7.32^2 + Ro Ri delta^2 with delta <= 0.75 / Ri
    ro, ri = gt.INNER_RADIUS + 7.32, gt.INNER_RADIUS
    assert np.all(d_near >= 7.32 - 1e-9) and np.all(d_near <= np.hypot(7.32, 0.75 * np.sqrt(ro / ri)) + 1e-9)
    assert gf.lane_rmse(inner, outer, pairing="index") > 10.0   # slanted pairs
    assert d_index.shape == (len(inner),)


@given(st.integers(0, 2**32 - 1), st.sampled_from([(), (3,), (2, 2)]), st.integers(1, 40), st.integers(1, 40),
       st.sampled_from([0.0, 1e3, 7.1e6]))
def test_nearest_pairing_equals_brute_force(seed, batch, ni, no, offset):
    """The matrix-product search of the nearest inner point returns the brute-force minimum exactly,
    with broadcasting of the batch axes and far from the origin (UTM-sized coordinates)."""
    rng = np.random.default_rng(seed)
    inner = offset + rng.uniform(-60, 60, batch + (ni, 2))
    outer = offset + rng.uniform(-60, 60, (no, 2))           # broadcast against inner's batch
    brute = np.linalg.norm(outer[..., :, None, :] - inner[..., None, :, :], axis=-1).min(-1)
    got = gf.lane_distances(inner, outer)
    assert got.shape == batch + (no,)
    # a different choice between near-ties: centring costs eps * offset per coordinate, so d^2 can be
    # misjudged by ~ 4 * 120 m * eps * offset and d by that over 2 d; the distance itself is exact
    tol = 1e-12 + 240 * np.finfo(float).eps * max(offset, 1.0) / np.maximum(brute, 1e-300)
    assert np.all(np.abs(got - brute) <= tol)
    chunked = gf._nearest_distances(inner, np.broadcast_to(outer, batch + (no, 2)), max_elements=1)
    np.testing.assert_array_equal(chunked, got)


def test_lane_metric_bad_input():
    with pytest.raises(ValueError, match="pairing"):
        gf.lane_distances(np.zeros((3, 2)), np.zeros((3, 2)), "closest")
    with pytest.raises(ValueError, match="inner"):
        gf.lane_distances(np.zeros((3, 3)), np.zeros((3, 2)))
    with pytest.raises(ValueError, match="separation"):
        gf.lane_rmse(np.zeros((3, 2)), np.zeros((3, 2)), separation=0.0)


# --- the world and the committed logs -----------------------------------------------------------------

def test_track_geometry():
    for radius, length in ((gt.INNER_RADIUS, 400.0), (gt.INNER_RADIUS + gt.LANE_SEPARATION, 446.0)):
        s = np.linspace(0, 2 * gt.STRAIGHT + 2 * np.pi * radius, 4001)
        e, n, h = gt.stadium_point(s, radius)
        steps = np.hypot(np.diff(e), np.diff(n))
        assert steps.sum() == pytest.approx(length, abs=0.05)
        np.testing.assert_allclose(steps, steps[0], rtol=1e-4)   # arc length parametrisation
        # heading is the direction of motion
        mid = np.arctan2(np.diff(n), np.diff(e))
        np.testing.assert_allclose(np.cos(mid - h[:-1]), 1.0, atol=1e-5)
    assert gt.LANE_SEPARATION == pytest.approx(7.32)


def test_gauss_markov_stationary_variance_and_correlation():
    rng = np.random.default_rng(3)
    b = gt.gauss_markov_errors(rng, 200, [1.0, 2.0], [50.0, 50.0], rho=-0.4, size=(400,))
    runs = 400 * 200
    # stationary variance (correlated samples: loose chi-square-style bound by effective count)
    var = b.reshape(-1, 2).var(axis=0)
    n_eff = 400 * 200 / (2 * 50)
    assert np.all(np.abs(var / np.array([1.0, 4.0]) - 1) < 4 * np.sqrt(2 / n_eff))
    corr = np.corrcoef(b.reshape(-1, 2).T)[0, 1]
    assert abs(corr + 0.4) < 4 / np.sqrt(n_eff)
    assert runs > 0
    with pytest.raises(ValueError, match="rho"):
        gt.gauss_markov_errors(rng, 10, [1, 1], [1, 1], rho=-1.5)


def test_committed_logs_equal_a_fresh_generation(tmp_path):
    fresh = gt.write_track_logs(tmp_path)
    for path in fresh:
        committed = gt.data_dir() / "gps_track" / path.name
        assert committed.read_bytes() == path.read_bytes(), f"{committed} differs from write_track_logs()"


@pytest.fixture(scope="module")
def logs():
    return gt.load_track_logs()


def test_committed_logs_skip_report(logs):
    runs, reports = logs
    for rec in gt.RECEIVERS:
        c = reports[rec.name].counts
        assert c["bad_checksum"] == 2 and c["truncated"] == 2 and c["non_utf8"] == 1 and c["malformed"] == 2
        assert c["unsupported"] == gt.RUNS
        assert c["no_fix"] == gt.RUNS * 3 * (2 if rec.gga else 1)
    assert not np.isnan(runs.inner).any() and not np.isnan(runs.outer).any()
    assert runs.inner.shape == (gt.RUNS, len(runs.truth_inner), 2, 4)


def test_fused_rmse_below_both_receivers(logs):
    runs, _ = logs
    T_i, T_o = runs.inner.shape[1], runs.outer.shape[1]

    def filt(z, r):
        zs = np.moveaxis(z.reshape(z.shape[0], z.shape[1], 4 * r), 1, 0)
        return gf.speed_heading_filter(zs, zs[0, :, :4], 10 * np.eye(4), np.eye(4), 0.05 * np.eye(4 * r)).x

    def rmse(fi, fo):
        return gf.lane_rmse(np.moveaxis(fi, 0, 1)[..., :2], np.moveaxis(fo, 0, 1)[..., :2])

    fused = rmse(filt(runs.inner, 2), filt(runs.outer, 2)).mean()
    for j in range(2):
        raw = gf.lane_rmse(runs.inner[:, :, j, :2], runs.outer[:, :, j, :2]).mean()
        single = rmse(filt(runs.inner[:, :, j], 1), filt(runs.outer[:, :, j], 1)).mean()
        assert fused < raw and fused < single
        assert abs(single - raw) < 0.02     # thesis tuning: K ~ 0.95, the filter passes the measurement
    assert T_i < T_o


def test_kalman_predict_agrees_with_model_mean():
    x = np.array([1.0, 2.0, 1.5, 0.7])
    A = gf.thesis_transition(x[3])
    xp, _ = predict(x, np.eye(4), A, np.eye(4))
    np.testing.assert_allclose(xp[:2], [1 + 1.5 * np.cos(0.7), 2 + 1.5 * np.sin(0.7)])


# --- Gauss-Markov bias states ---------------------------------------------------------------------

@given(tau1=st.floats(5, 500), tau2=st.floats(5, 500) | st.just(None), rho=st.floats(-0.9, 0.9),
       dt=st.floats(0.1, 5))
def test_bias_model_keeps_the_stationary_bias_covariance(tau1, tau2, rho, dt):
    tau2 = tau1 if tau2 is None else tau2
    m = gf.gauss_markov_bias_model(dt, 0.1, [1.3, 2.0], [tau1, tau2], rho, [0.3, 0.4], [0.1, 0.2])
    n = 4
    for a in range(2):
        b = slice(a * n + 2, a * n + 4)
        Pb = m.P0[b, b]
        np.testing.assert_allclose(m.F[b, b] @ Pb @ m.F[b, b].T + m.Q[b, b], Pb, atol=1e-12)
        np.testing.assert_allclose(np.diag(Pb), [1.69, 4.0], rtol=1e-12)
        if tau1 == tau2:
            np.testing.assert_allclose(Pb[0, 1], rho * 2.6, atol=1e-12)
    np.testing.assert_allclose(m.Q, m.Q.T)
    assert np.linalg.eigvalsh(m.Q).min() > -1e-12


def test_bias_model_measurement_map():
    m = gf.gauss_markov_bias_model(1.0, 0.1, [1.0, 2.0], [100.0, 100.0], 0.0, [0.3, 0.4], [0.1, 0.2])
    x = np.array([10.0, 1.0, 0.5, -0.7, 20.0, -2.0, 0.2, 0.9])   # [x, vx, b1x, b2x, y, vy, b1y, b2y]
    np.testing.assert_allclose(m.H @ x, [10.5, 20.2, 1.0, -2.0, 9.3, 20.9, 1.0, -2.0])
    np.testing.assert_allclose(np.diag(m.R), [0.09, 0.09, 0.01, 0.01, 0.16, 0.16, 0.04, 0.04])
    z = np.array([[1.0, 2.0, 2.0, np.pi / 2], [3.0, 4.0, 1.0, 0.0]])
    np.testing.assert_allclose(gf.velocity_measurements(z), [1, 2, 0, 2, 3, 4, 1, 0], atol=1e-15)


def test_bias_model_bad_input():
    with pytest.raises(ValueError, match="tau"):
        gf.gauss_markov_bias_model(1.0, 0.1, [1.0], [-1.0], 0.0, [0.3], [0.1])
    with pytest.raises(ValueError, match="rho"):
        gf.gauss_markov_bias_model(1.0, 0.1, [1.0, 1.0], [1.0, 1.0], -1.5, [0.3, 0.3], [0.1, 0.1])
    with pytest.raises(ValueError, match=r"^tau must be a scalar or have shape \(2,\)"):  # 3 taus, 2 receivers
        gf.gauss_markov_bias_model(1.0, 0.1, [1.0, 2.0], [1.0, 2.0, 3.0], 0.1, 1.0, 1.0)
    with pytest.raises(ValueError, match=r"^z must"):
        gf.velocity_measurements(np.zeros(4))


def test_bias_state_with_doppler_beats_raw_single_receiver(logs):
    runs, _ = logs
    rec = gt.RECEIVERS[0]
    m = gf.gauss_markov_bias_model(1.0, 0.05, [rec.sigma_gm], [rec.tau], 0.0, [rec.sigma_white], [rec.sigma_vel])
    est = [np.moveaxis(gf.bias_state_positions(np.moveaxis(lap[:, :, :1], 1, 0), m), 0, 1)
           for lap in (runs.inner, runs.outer)]
    raw = gf.lane_rmse(runs.inner[:, :, 0, :2], runs.outer[:, :, 0, :2]).mean()
    assert gf.lane_rmse(*est).mean() < 0.9 * raw
    with pytest.raises(ValueError, match="receivers"):
        gf.bias_state_positions(np.moveaxis(runs.inner, 1, 0), m)

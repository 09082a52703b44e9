"""Tests of kftrack.ukf: sigma points against filterpy (test-only oracle), the unscented
transform exact for affine maps (hypothesis), the UKF on a linear model equals the Kalman
filter to round-off, circular means and wrapping across +-pi, bad input."""
from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import JulierSigmaPoints as FpJulier
from filterpy.kalman import MerweScaledSigmaPoints as FpMerwe
from filterpy.kalman import unscented_transform as fp_ut
from hypothesis import given, settings
from hypothesis import strategies as st

from kftrack import ekf, kalman, ukf
from kftrack.kernels import mv as _mv
from kftrack.sensors.radar import RangeBearing

EPS = np.finfo(float).eps


def random_spd(rng, n, scale=1.0):
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T + n * np.eye(n))


@pytest.mark.parametrize("alpha,beta,kappa", [(1.0, 2.0, 0.0), (0.5, 2.0, 1.0), (1e-3, 2.0, 0.0), (0.8, 0.0, -1.0)])
def test_merwe_points_match_filterpy(alpha, beta, kappa):
    rng = np.random.default_rng(0)
    n = 4
    x, P = rng.normal(size=n), random_spd(rng, n)
    ours = ukf.MerweScaledSigmaPoints(alpha, beta, kappa)(x, P)
    fp = FpMerwe(n, alpha=alpha, beta=beta, kappa=kappa)
    assert np.allclose(ours.X, fp.sigma_points(x, P), rtol=1e-13, atol=1e-13)
    assert np.allclose(ours.Wm, fp.Wm, rtol=1e-13) and np.allclose(ours.Wc, fp.Wc, rtol=1e-13)


@pytest.mark.parametrize("kappa", [0.0, 1.0, -1.0])
def test_julier_points_match_filterpy(kappa):
    rng = np.random.default_rng(1)
    n = 3
    x, P = rng.normal(size=n), random_spd(rng, n)
    ours = ukf.JulierSigmaPoints(kappa)(x, P)
    fp = FpJulier(n, kappa=kappa)
    assert np.allclose(ours.X, fp.sigma_points(x, P), rtol=1e-13, atol=1e-13)
    assert np.allclose(ours.Wm, fp.Wm, rtol=1e-13) and np.allclose(ours.Wc, fp.Wc, rtol=1e-13)


def test_sigma_points_reproduce_mean_and_covariance_and_broadcast():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(5, 3))
    P = np.stack([random_spd(rng, 3) for _ in range(5)])
    for pts in (ukf.MerweScaledSigmaPoints(0.7, 2.0, 0.5), ukf.JulierSigmaPoints(1.0)):
        sp = pts(x, P)
        assert sp.X.shape == (5, 7, 3)
        assert np.isclose(sp.Wm.sum(), 1.0, rtol=0, atol=10 * EPS)
        m, C = ukf.weighted_moments(sp.X, sp.Wm, sp.Wm)  # the mean weights recover P exactly
        assert np.allclose(m, x, atol=1e-13)
        assert np.allclose(C, P, rtol=1e-12)


def test_unscented_transform_matches_filterpy_on_polar_to_cartesian():
    x, P = np.array([1.0, 0.3]), np.diag([0.02**2, 0.35**2])
    pol = lambda s: np.stack([s[..., 0] * np.cos(s[..., 1]), s[..., 0] * np.sin(s[..., 1])], axis=-1)
    pts = ukf.MerweScaledSigmaPoints(0.9, 2.0, 0.0)
    ours = ukf.unscented_transform(pol, x, P, pts)
    fp = FpMerwe(2, alpha=0.9, beta=2.0, kappa=0.0)
    m, C = fp_ut(pol(fp.sigma_points(x, P)), fp.Wm, fp.Wc)
    assert np.allclose(ours.mean, m, rtol=1e-13) and np.allclose(ours.cov, C, rtol=1e-12)


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 5), d=st.integers(1, 4), alpha=st.floats(0.2, 1.0),
       kappa=st.floats(0.0, 3.0))
def test_unscented_transform_is_exact_for_affine_maps(seed, n, d, alpha, kappa):
    rng = np.random.default_rng(seed)
    A, b = rng.normal(size=(d, n)), rng.normal(size=d)
    x, P = rng.normal(size=n), random_spd(rng, n)
    t = ukf.unscented_transform(lambda v: v @ A.T + b, x, P, ukf.MerweScaledSigmaPoints(alpha, 2.0, kappa))
    # round-off of a sum scales with the sum of the magnitudes of its terms (|A| |P| |A|^T, not
    # |A P A^T|, which cancellation can make small), times 1/alpha^2 for the weights W_0 ~ -1/alpha^2
    scale = np.max(np.abs(A) @ np.abs(P) @ np.abs(A).T) / alpha**2
    scale_cross = np.max(np.abs(P) @ np.abs(A).T) / alpha**2
    assert np.allclose(t.mean, A @ x + b, rtol=0, atol=1e3 * EPS * (1 + np.max(np.abs(A @ x + b))) / alpha**2)
    assert np.allclose(t.cov, A @ P @ A.T, rtol=0, atol=1e3 * EPS * scale)
    assert np.allclose(t.cross, P @ A.T, rtol=0, atol=1e3 * EPS * scale_cross)
    assert np.allclose(t.cov, t.cov.T, rtol=0, atol=0)


@pytest.mark.parametrize("points", [ukf.MerweScaledSigmaPoints(), ukf.JulierSigmaPoints(1.0),
                                    ukf.MerweScaledSigmaPoints(0.5, 2.0, 1.0)])
def test_ukf_on_linear_model_equals_kalman_filter_to_round_off(points):
    rng = np.random.default_rng(7)
    n, m, T, N = 4, 2, 30, 5
    F = np.eye(n) + 0.2 * rng.normal(size=(n, n))
    Q, H, R = random_spd(rng, n, 0.1), rng.normal(size=(m, n)), random_spd(rng, m)
    x0, P0 = rng.normal(size=n), random_spd(rng, n)
    f, h = (lambda x: _mv(F, x)), (lambda x: _mv(H, x))
    _, zs = ekf.simulate_additive_gaussian(f, h, x0, P0, Q, R, T, rng, runs=N)
    zs[5, 2] = np.nan
    kf = kalman.kalman_filter(zs, x0, P0, F, Q, H, R)
    uk = ukf.unscented_kalman_filter(zs, x0, P0, f, Q, h, R, points)
    # Round-off bound: each of the T steps perturbs a result by at most ~ n * w * kappa * eps
    # relative: sigma-point sums of 2n+1 terms with weights up to w = sum|W|, a Cholesky factor and
    # a solve whose condition is at most kappa = max cond(P); the stable filter does not amplify
    # earlier errors, so the steps add (observed: at most ~75 eps * scale, well inside the bound).
    Wm, Wc, _ = points.weights(n)
    w = max(np.abs(Wm).sum(), np.abs(Wc).sum())
    kappa = np.linalg.cond(kf.P_prior).max()
    for name, a, b in zip(kf._fields, kf, uk):
        scale = np.nanmax(np.abs(a)) + 1.0
        assert np.allclose(a, b, rtol=0, atol=T * n * w * kappa * EPS * scale, equal_nan=True), name
    assert np.array_equal(np.isnan(kf.nis), np.isnan(uk.nis))


def test_circular_mean_across_pi():
    Y = np.array([[np.pi - 0.1], [-np.pi + 0.1], [np.pi - 0.05], [-np.pi + 0.05], [np.pi]])
    W = np.full(5, 0.2)
    m, C = ukf.weighted_moments(Y, W, W, angle_components=[0])
    assert np.isclose(abs(m[0]), np.pi, atol=1e-14)
    assert np.isclose(C[0, 0], (2 * 0.1**2 + 2 * 0.05**2) / 5, rtol=1e-9)
    m_naive, _ = ukf.weighted_moments(Y, W, W)
    assert abs(m_naive[0]) < 1.0  # what goes wrong without it


def _rotate(x, phi):
    c, s = np.cos(phi), np.sin(phi)
    Rm = np.array([[c, -s], [s, c]])
    out = x.copy()
    out[..., [0, 2]] = x[..., [0, 2]] @ Rm.T
    out[..., [1, 3]] = x[..., [1, 3]] @ Rm.T
    return out


def _ekf_update(x, P, z, radar, angles):
    return ekf.ekf_update(x, P, z, radar.h, radar.jacobian, radar.R, angles)


def _ukf_update(x, P, z, radar, angles):
    return ukf.ukf_update(x, P, z, radar.h, radar.R, angle_components=angles)


@pytest.mark.parametrize("update", [_ekf_update, _ukf_update], ids=["ekf", "ukf"])
def test_update_near_bearing_pi_matches_rotated_geometry(update):
    """A target just across the +-pi cut gives the same update as the geometry rotated by pi
    (where nothing wraps); forgetting the angle component gives an innovation of ~2 pi."""
    radar = RangeBearing(sigmas=(5.0, 0.01))
    x = np.array([-1000.0, 0.0, 3.0, 0.0])  # bearing just below pi
    P = np.diag([400.0, 1.0, 900.0, 1.0])  # the UKF's bearing sigma points straddle the cut
    z = np.array([1000.0, -np.pi + 0.002])  # measured just above -pi
    up = update(x, P, z, radar, radar.angle_components)
    assert abs(up.y[1]) < 0.01
    zr = np.array([z[0], ekf.wrap_angle(z[1] + np.pi)])
    ur = update(_rotate(x, np.pi), P, zr, radar, radar.angle_components)
    assert np.allclose(_rotate(ur.x, -np.pi), up.x, atol=1e-8)
    assert np.allclose(ur.S, up.S, rtol=1e-9) and np.isclose(ur.nis, up.nis, rtol=1e-6)
    assert abs(update(x, P, z, radar, ()).y[1]) > 1.0


def test_state_angle_is_wrapped_after_update():
    # state [heading]; measure the heading directly; prior just below pi, measurement just above -pi.
    # The precise measurement pulls the mean across the cut: pi - 0.01 + K * 0.02 with K = P / (P + R)
    # exceeds pi, so the state must come back wrapped to just above -pi (with equal variances the
    # mean would land on pi exactly and the test could not tell wrapping from no wrapping).
    h = lambda x: x
    P, R = 0.01, 1e-4
    up = ukf.ukf_update([np.pi - 0.01], [[P]], [-np.pi + 0.01], h, [[R]], angle_components=[0],
                        state_angles=[0])
    expected = np.pi - 0.01 + P / (P + R) * 0.02 - 2 * np.pi
    assert -np.pi < up.x[0] <= np.pi
    assert up.x[0] == pytest.approx(expected, abs=1e-12)
    assert up.y[0] == pytest.approx(0.02, abs=1e-12)  # the innovation is wrapped as well


def test_predicted_mean_of_a_state_angle_across_pi():
    """f wraps its output, so the images of the sigma points straddle the cut: the circular
    mean and wrapped spread give the translated Gaussian (exact for a translation); the plain
    mean lands near zero, on the wrong side of the circle."""
    f = lambda x: np.concatenate([ekf.wrap_angle(x[..., :1] + 0.2), x[..., 1:]], axis=-1)  # noqa: E731
    x, P, Q = np.array([np.pi - 0.1, 1.0]), np.diag([0.15**2, 0.5]), np.diag([1e-4, 1e-3])
    xp, Pp = ukf.ukf_predict(x, P, f, Q, state_angles=[0])
    assert xp[0] == pytest.approx(np.pi + 0.1 - 2 * np.pi, abs=1e-12) and xp[1] == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(Pp, P + Q, rtol=1e-12, atol=1e-15)
    xn, Pn = ukf.ukf_predict(x, P, f, Q)
    assert abs(xn[0]) < 2.0 and Pn[0, 0] > 1.0  # what goes wrong without it


def test_bad_input_names_the_argument():
    x, P = np.zeros(2), np.eye(2)
    with pytest.raises(TypeError, match="points"):
        ukf.ukf_predict(x, P, lambda v: v, np.eye(2), points="merwe")
    with pytest.raises(ValueError, match="P must be positive semi-definite"):
        ukf.MerweScaledSigmaPoints()(x, np.diag([1.0, -1.0]))
    with pytest.raises(ValueError, match="alpha"):
        ukf.MerweScaledSigmaPoints(alpha=0.0)
    with pytest.raises(ValueError, match="kappa"):
        ukf.JulierSigmaPoints(kappa=-2.0)(x, P)
    with pytest.raises(ValueError, match="state_angles"):
        ukf.ukf_predict(x, P, lambda v: v, np.eye(2), state_angles=[2])
    with pytest.raises(ValueError, match="fn"):
        ukf.unscented_transform(lambda v: v[..., 0], x, P)
    with pytest.raises(ValueError, match="Wm"):
        ukf.weighted_moments(np.zeros((5, 2)), np.ones(4), np.ones(5))
    with pytest.raises(ValueError, match=r"^R must"):
        ukf.ukf_update(x, P, x, lambda v: v, -np.eye(2))


def test_linear_measurement_matrix_equals_the_kalman_update_to_round_off():
    rng = np.random.default_rng(13)
    n, m, N = 4, 2, 5
    A = rng.normal(size=(n, n))
    H, R = rng.normal(size=(m, n)), np.eye(m) + 0.1 * np.ones((m, m))
    x, P, z = rng.normal(size=(N, n)), A @ A.T + n * np.eye(n), rng.normal(size=(N, m))
    u = ukf.ukf_update(x, P, z, H, R)  # h given as the (m, n) matrix H
    same = ukf.ukf_update(x, P, z, lambda s: _mv(H, s), R)  # the matrix is the callable H x, bit for bit
    for name, a, b in zip(same._fields, same, u):
        assert np.array_equal(a, b), name
    ref = kalman.update(x, P, z, H, R)
    # Round-off bound (one step, first order). The sigma points use the Cholesky factor L of c P
    # (backward error |dP| <= n eps |P|), and Pzz = sum_i W_i (H dX_i)(H dX_i)^T sums 2n + 1 terms of size
    # <= |H|^2 |P| (Frobenius), so |dS| <= eS = (2n + 1 + n) (m + n) eps |H|^2 |P| (+ the few eps of the KF's own
    # S). The gain K = Pxz S^-1 then errs by at most cond(S) eS / |S| relative, and x, P inherit it times |y|
    # and |K||S||K| + |P|. Every term is size x condition x eps, computed here from the data.
    nH, nP = np.linalg.norm(H), np.linalg.norm(P)
    eS = (3 * n + 1) * (m + n) * EPS * nH**2 * nP
    S = ref.S
    relK = np.linalg.cond(S).max() * eS / np.linalg.norm(S, axis=(-2, -1)).min() + (m + n) * EPS * np.linalg.cond(S).max()
    nK = np.linalg.norm(ref.K, axis=(-2, -1)).max()
    bounds = {"S": eS, "K": relK * nK, "y": (n + 1) * EPS * (nH * np.abs(x).max() * 2 + np.abs(z).max()),
              "x": relK * nK * np.abs(ref.y).max() * 2 + (n + 1) * EPS * np.abs(x).max(),
              "P": 3 * relK * nK**2 * np.linalg.norm(S, axis=(-2, -1)).max() + (n + 1) * EPS * nP * 4}
    for name in ("S", "K", "y", "x", "P"):
        err = np.max(np.abs(getattr(u, name) - getattr(ref, name)))
        assert err <= bounds[name], (name, err, bounds[name])
    assert np.allclose(u.nis, ref.nis, rtol=1e-10) and np.allclose(u.loglik, ref.loglik, rtol=1e-10)
    with pytest.raises(ValueError, match=r"h must have shape \(\.\.\., 2, 4\)"):
        ukf.ukf_update(x, P, z, H[:, :3], R)
    # the whole-sequence filter takes the matrix too, identical to the callable
    F = np.eye(n) + 0.1 * rng.normal(size=(n, n))
    zs = rng.normal(size=(6, N, m))
    a = ukf.unscented_kalman_filter(zs, x[0], P, lambda s: _mv(F, s), 0.1 * np.eye(n), H, R)
    b = ukf.unscented_kalman_filter(zs, x[0], P, lambda s: _mv(F, s), 0.1 * np.eye(n), lambda s: _mv(H, s), R)
    for name, p_, q_ in zip(a._fields, a, b):
        assert np.array_equal(p_, q_, equal_nan=True), name

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

from closed_forms import roundoff_tol, scaled_cond
from kftrack import ekf, kalman, ukf
from kftrack.kernels import mv as _mv
from kftrack.sensors.radar import RangeBearing

EPS = np.finfo(float).eps


def random_spd(rng, n, scale=1.0):
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T + n * np.eye(n))


def _points_tols(x, P, Wm, Wc, spread):
    """Round-off bounds for two codes computing the sigma points x +- sqrt(c) L_i and their weights.

    Cholesky's forward error is <= n cond(P) eps |L| (Higham 2002, Thm 10.8, to first order), so the
    points differ by <= that times sqrt(c) plus the addition's u |x|. The weights are a handful of
    operations: W_0 (lambda = alpha^2 (n + kappa) - n, lambda / c, + 1 - alpha^2 + beta) <= 4
    roundings of terms of size |W_0| + 1 + |Wc_0 - Wm_0| each way (absolute); W_i = 1 / (2c), i >= 1,
    <= 3 roundings without cancellation each way: relative 6 u = 3 eps (rtol 4 eps)."""
    n = len(x)
    L = np.abs(np.linalg.cholesky(P))
    tol_X = roundoff_tol(np.abs(x).max() + np.sqrt(spread) * L.max(), n, np.linalg.cond(P))
    tol_W0 = roundoff_tol(np.abs(Wm[0]) + 1.0 + np.abs(Wc[0] - Wm[0]), 4)
    return tol_X, tol_W0, 4 * EPS


def _weights_close(ours, fp, tol_W0, rtol_W):
    for a, b in ((ours.Wm, fp.Wm), (ours.Wc, fp.Wc)):
        assert abs(a[0] - b[0]) <= tol_W0
        np.testing.assert_allclose(a[1:], b[1:], rtol=rtol_W, atol=0)


def _ut_scales(X, W, m):
    """Sum of the magnitudes of the terms of sum_i W_i X_i and of sum_i W_i (X_i - m)(X_i - m)^T:
    a sum's round-off scales with these (not with the result, which cancellation can make small)."""
    aW, D = np.abs(W), np.abs(X - m[..., None, :])
    return (aW[:, None] * np.abs(X)).sum(-2).max(), np.einsum("i,...ij,...ik->...jk", aW, D, D).max()


@pytest.mark.parametrize("alpha,beta,kappa", [(1.0, 2.0, 0.0), (0.5, 2.0, 1.0), (1e-3, 2.0, 0.0), (0.8, 0.0, -1.0)])
def test_merwe_points_match_filterpy(alpha, beta, kappa):
    rng = np.random.default_rng(0)
    n = 4
    x, P = rng.normal(size=n), random_spd(rng, n)
    ours = ukf.MerweScaledSigmaPoints(alpha, beta, kappa)(x, P)
    fp = FpMerwe(n, alpha=alpha, beta=beta, kappa=kappa)
    tol_X, *tol_W = _points_tols(x, P, ours.Wm, ours.Wc, alpha**2 * (n + kappa))
    np.testing.assert_allclose(ours.X, fp.sigma_points(x, P), rtol=0, atol=tol_X)
    _weights_close(ours, fp, *tol_W)


@pytest.mark.parametrize("kappa", [0.0, 1.0, -1.0])
def test_julier_points_match_filterpy(kappa):
    rng = np.random.default_rng(1)
    n = 3
    x, P = rng.normal(size=n), random_spd(rng, n)
    ours = ukf.JulierSigmaPoints(kappa)(x, P)
    fp = FpJulier(n, kappa=kappa)
    tol_X, *tol_W = _points_tols(x, P, ours.Wm, ours.Wc, n + kappa)
    np.testing.assert_allclose(ours.X, fp.sigma_points(x, P), rtol=0, atol=tol_X)
    _weights_close(ours, fp, *tol_W)


def test_sigma_points_reproduce_mean_and_covariance_and_broadcast():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(5, 3))
    P = np.stack([random_spd(rng, 3) for _ in range(5)])
    for pts in (ukf.MerweScaledSigmaPoints(0.7, 2.0, 0.5), ukf.JulierSigmaPoints(1.0)):
        sp = pts(x, P)
        assert sp.X.shape == (5, 7, 3)
        assert np.isclose(sp.Wm.sum(), 1.0, rtol=0, atol=10 * EPS)
        m, C = ukf.weighted_moments(sp.X, sp.Wm, sp.Wm)  # the mean weights recover P exactly
        # sums of 2n + 1 terms (scales from _ut_scales) on points whose Cholesky factor has backward
        # error L L^T = P + dP, |dP| <= (n + 1) u |L||L|^T (Higham 2002, Thm 10.3): no cond(P) needed
        s_m, s_C = _ut_scales(sp.X, sp.Wm, x)
        LL = np.abs(np.linalg.cholesky(P)) @ np.abs(np.linalg.cholesky(P)).swapaxes(-1, -2)
        np.testing.assert_allclose(m, x, rtol=0, atol=roundoff_tol(s_m, 2 * 3 + 1))
        np.testing.assert_allclose(C, P, rtol=0, atol=roundoff_tol(s_C, 2 * 3 + 1) + roundoff_tol(LL, 3 + 1))


def test_unscented_transform_matches_filterpy_on_polar_to_cartesian():
    x, P = np.array([1.0, 0.3]), np.diag([0.02**2, 0.35**2])
    pol = lambda s: np.stack([s[..., 0] * np.cos(s[..., 1]), s[..., 0] * np.sin(s[..., 1])], axis=-1)
    pts = ukf.MerweScaledSigmaPoints(0.9, 2.0, 0.0)
    ours = ukf.unscented_transform(pol, x, P, pts)
    fp = FpMerwe(2, alpha=0.9, beta=2.0, kappa=0.0)
    Y = pol(fp.sigma_points(x, P))
    m, C = fp_ut(Y, fp.Wm, fp.Wc)
    # P is diagonal: both Cholesky factors are its square roots, correctly rounded; the points and
    # their images (cos, sin, a product: <= 3 u relative) then the sums of 2n + 1 terms each way
    s_m, s_C = _ut_scales(Y, fp.Wm, m)
    np.testing.assert_allclose(ours.mean, m, rtol=0, atol=roundoff_tol(s_m, 2 * 2 + 1 + 3))
    np.testing.assert_allclose(ours.cov, C, rtol=0, atol=roundoff_tol(s_C, 2 * 2 + 1 + 3))


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 5), d=st.integers(1, 4), alpha=st.floats(0.2, 1.0),
       kappa=st.floats(0.0, 3.0))
def test_unscented_transform_is_exact_for_affine_maps(seed, n, d, alpha, kappa):
    rng = np.random.default_rng(seed)
    A, b = rng.normal(size=(d, n)), rng.normal(size=d)
    x, P = rng.normal(size=n), random_spd(rng, n)
    t = ukf.unscented_transform(lambda v: v @ A.T + b, x, P, ukf.MerweScaledSigmaPoints(alpha, 2.0, kappa))
    # round-off of a sum scales with the sum of the magnitudes of its terms (_ut_scales: not with
    # |A P A^T|, which cancellation can make small; W_0 ~ -1/alpha^2 enters through |W|): the 2n + 1
    # terms, each image a length-n product (n u); the points' Cholesky backward error
    # |dP| <= (n + 1) u |L||L|^T maps to |A| |dP| |A|^T (cov) and |dP| |A|^T (cross). The deviations
    # D_i = Y_i - mean carry the images' and the mean's absolute round-off e_D (size |A||X_i| + |b|,
    # which a large b makes much larger than D: at first derived without it, hypothesis found
    # b ~ 1, |A| sqrt(P) ~ 2e-3 with a relative error 3e-14 in the covariance), adding
    # sum |W_i| 2 |D_i| e_D to the covariance and sum |W_i| (|DX_i| e_D + e_X |D_i|) to the cross term
    sp = ukf.MerweScaledSigmaPoints(alpha, 2.0, kappa)(x, P)
    Y = sp.X @ A.T + b
    s_m, s_C = _ut_scales(Y, sp.Wm, A @ x + b)
    s_C = max(s_C, _ut_scales(Y, sp.Wc, A @ x + b)[1])
    aW, DX, DY = np.abs(sp.Wc), np.abs(sp.X - x), np.abs(Y - (A @ x + b))
    s_X = np.einsum("i,ij,ik->jk", aW, DX, DY).max()
    L = np.abs(np.linalg.cholesky(P))
    LL = L @ L.T
    k = 2 * n + 1 + n
    tol_m = roundoff_tol(s_m, k)
    e_D = roundoff_tol(np.abs(sp.X) @ np.abs(A).T + np.abs(b), n + 1) + tol_m
    e_X = roundoff_tol(sp.X, 2)
    tol_C = roundoff_tol(s_C, k) + 2 * (aW * DY.max(-1)).sum() * e_D + e_D**2 * aW.sum()
    tol_X = roundoff_tol(s_X, k) + (aW * (DX.max(-1) * e_D + e_X * DY.max(-1))).sum()
    np.testing.assert_allclose(t.mean, A @ x + b, rtol=0, atol=tol_m)
    np.testing.assert_allclose(t.cov, A @ P @ A.T, rtol=0, atol=tol_C + roundoff_tol(np.abs(A) @ LL @ np.abs(A).T, n + 1))
    np.testing.assert_allclose(t.cross, P @ A.T, rtol=0, atol=tol_X + roundoff_tol(LL @ np.abs(A).T, n + 1))
    np.testing.assert_array_equal(t.cov, t.cov.T)


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
    # circular mean atan2(sum W sin y, sum W cos y): sin, cos within 1 ulp, sums of 5 terms, atan2
    # within 1 ulp, on a result of size pi: <= (5 + 2) eps pi (c = 1)
    d_m = roundoff_tol(np.pi, 5 + 2, c=1.0)
    assert abs(abs(m[0]) - np.pi) <= d_m
    # the wrapped deviations (pi - 0.05 etc., rounded literals: 2 eps pi) err by <= d_m + 2 eps pi,
    # the smallest is 0.05: their squares' relative error is <= 2 (d_m + 2 eps pi) / 0.05, plus the
    # 5-term sum's 5 u
    d_rel = 2 * (d_m + 2 * EPS * np.pi) / 0.05 + 5 * EPS
    assert C[0, 0] == pytest.approx((2 * 0.1**2 + 2 * 0.05**2) / 5, rel=d_rel, abs=0)
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
    # The two problems differ by round-off in their inputs: the rotation (sin(pi) = 1.2e-16, two
    # products and a sum: dx <= 2 eps |x|) and the wrapped bearing (dz <= eps pi). The update maps
    # them through I - K J (J = dh/dx, the EKF's H and the UKF's linearization) and K; its own
    # round-off is a solve with S, whose error follows the condition number of S scaled to unit
    # diagonal (scaled_cond: metres and radians inflate cond(S) to 4e5 without losing accuracy),
    # and sums of 2n + 1 sigma-point terms of total weight w (1 for the EKF). Rotating back adds 2 eps |x|.
    J = radar.jacobian(x)
    n, K = 4, up.K
    w = np.abs(ukf.MerweScaledSigmaPoints().weights(n)[1]).sum() if update is _ukf_update else 1.0
    dx, dz = roundoff_tol(x, 2, c=1.0), roundoff_tol(np.pi, 1, c=1.0)
    dy = np.abs(J).sum(1).max() * dx + dz
    cS = scaled_cond(up.S)
    tol_x = (roundoff_tol(np.abs(x).max() + np.abs(K) @ np.abs(up.y), (2 * n + 1) * w + 2, cS)
             + np.linalg.norm(np.eye(n) - K @ J, np.inf) * dx + np.linalg.norm(K, np.inf) * dz + roundoff_tol(up.x, 2, c=1.0))
    np.testing.assert_allclose(_rotate(ur.x, -np.pi), up.x, rtol=0, atol=tol_x)
    # S entrywise: a product's round-off is entrywise <= gamma |J| |P| |J|^T (Higham 2002, (3.13));
    # the UKF's sum_i Wc_i D_i D_i^T over the images' deviations D_i (wrapped bearing) has terms of
    # size sum |Wc| |D| |D|^T, larger off the diagonal than |J| P |J|^T (second-order range
    # deviations of the points that move across the line of sight; measured first with the EKF's
    # scale, which the UKF exceeded tenfold). dx moves them by a relative 2 dx / |x|, S by twice that
    # (UKF: D_i themselves carry the images' absolute round-off e_D, range ~ 1000 m, and the shift
    # |J| dx of the rotated inputs: sum |W_i| (|D_i| e_D^T + e_D |D_i|^T) more, as in the affine test)
    k_S = (2 * n + 1) * w + n + 1
    if update is _ukf_update:
        sp = ukf.MerweScaledSigmaPoints()(x, P)
        Z = radar.h(sp.X)
        D = np.abs(Z - radar.h(x))
        D[..., 1] = np.abs(ekf.wrap_angle(Z[..., 1] - radar.h(x)[1]))
        aW = np.abs(sp.Wc)
        S_scale = np.einsum("i,ij,ik->jk", aW, D, D) + radar.R
        e_D = roundoff_tol(1.0, k_S) * np.array([np.abs(Z[..., 0]).max(), np.pi]) + np.abs(J).sum(1) * dx
        E = np.einsum("i,ij->j", aW, D)
        tol_S = roundoff_tol(1.0, k_S) * S_scale + np.outer(E, e_D) + np.outer(e_D, E) + aW.sum() * np.outer(e_D, e_D)
    else:
        S_scale = np.abs(J) @ P @ np.abs(J).T + radar.R
        tol_S = (roundoff_tol(1.0, k_S) + 4 * dx / np.abs(x).max()) * S_scale
    assert np.all(np.abs(ur.S - up.S) <= tol_S), (np.abs(ur.S - up.S), tol_S)
    # nis = y^T S^-1 y: d nis <= 2 |S^-1 y| dy + (its own) nis cond eps, plus dS's share nis |S^-1| |dS|
    Sinv_y = np.linalg.solve(up.S, up.y)
    tol_nis = 2 * np.abs(Sinv_y).sum() * dy + roundoff_tol(up.nis, 2, cS) + up.nis * np.abs(tol_S).sum() / np.linalg.eigvalsh(up.S)[0]
    assert abs(ur.nis - up.nis) <= tol_nis
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
    # scalar: the prior, the measurement and the wraps carry eps pi each (the literal 0.02 is rounded
    # too); the gain P / (P + R) a few u; the sums of 3 sigma points (n = 1) of total weight w
    w = np.abs(ukf.MerweScaledSigmaPoints().weights(1)[1]).sum()
    assert up.y[0] == pytest.approx(0.02, abs=roundoff_tol(np.pi, 3 * w + 3))  # the innovation is wrapped as well
    assert up.x[0] == pytest.approx(expected, abs=roundoff_tol(np.pi, 3 * w + 3) * 2)


def test_predicted_mean_of_a_state_angle_across_pi():
    """f wraps its output, so the images of the sigma points straddle the cut: the circular
    mean and wrapped spread give the translated Gaussian (exact for a translation); the plain
    mean lands near zero, on the wrong side of the circle."""
    f = lambda x: np.concatenate([ekf.wrap_angle(x[..., :1] + 0.2), x[..., 1:]], axis=-1)  # noqa: E731
    x, P, Q = np.array([np.pi - 0.1, 1.0]), np.diag([0.15**2, 0.5]), np.diag([1e-4, 1e-3])
    xp, Pp = ukf.ukf_predict(x, P, f, Q, state_angles=[0])
    # points on a circle of size pi: the wrap and the circular mean (sin, cos, atan2, sums of
    # 2n + 1 = 5 terms of total weight w) err by <= (5 w + 4) eps pi; the spread by the same
    # relative to the smallest deviation sqrt(c) 0.15 (c = alpha^2 n, squares: twice)
    pts = ukf.MerweScaledSigmaPoints()
    Wm, Wc, c = pts.weights(2)
    w = max(np.abs(Wm).sum(), np.abs(Wc).sum())
    d_ang = roundoff_tol(np.pi, 5 * w + 4, c=1.0)
    assert xp[0] == pytest.approx(np.pi + 0.1 - 2 * np.pi, abs=d_ang)
    assert xp[1] == pytest.approx(1.0, abs=roundoff_tol(1.0 + np.sqrt(c * 0.5), 5 * w))
    # entrywise: the points lie on the axes (P diagonal), so sum |W| |D_j| |D_k| = w c P_jj on the
    # diagonal and 0 off it; the angle deviations D_0 carry d_ang each, which adds w d_ang |D_k| to
    # row and column 0 (twice on [0, 0])
    sd = np.sqrt(c * np.diag(P))
    tol_P = roundoff_tol(1.0, 5 * w + 4) * (w * np.diag(sd**2) + np.abs(Q))
    tol_P[0, :] += w * d_ang * sd
    tol_P[:, 0] += w * d_ang * sd
    assert np.all(np.abs(Pp - (P + Q)) <= tol_P), (np.abs(Pp - (P + Q)), tol_P)
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
    # nis = y^T S^-1 y moves by <= 2 |S^-1 y| dy + nis |S^-1| dS, plus its own solve's cond(S) m eps
    # relative; log det S by <= m |S^-1| dS (tr(S^-1 dS)) plus m cond(S) m eps (the factorization)
    Sinv = np.linalg.norm(np.linalg.inv(S), 2, axis=(-2, -1))
    cS = np.linalg.cond(S)
    d_nis = (2 * np.linalg.norm(np.linalg.solve(S, ref.y[..., None])[..., 0], axis=-1) * np.sqrt(m) * bounds["y"]
             + ref.nis * Sinv * m * bounds["S"] + roundoff_tol(1.0, m, cS) * ref.nis)
    d_logdet = m * Sinv * m * bounds["S"] + roundoff_tol(1.0, m * m, cS)
    assert np.all(np.abs(u.nis - ref.nis) <= d_nis)
    assert np.all(np.abs(u.loglik - ref.loglik) <= 0.5 * (d_nis + d_logdet))
    with pytest.raises(ValueError, match=r"h must have shape \(\.\.\., 2, 4\)"):
        ukf.ukf_update(x, P, z, H[:, :3], R)
    # the whole-sequence filter takes the matrix too, identical to the callable
    F = np.eye(n) + 0.1 * rng.normal(size=(n, n))
    zs = rng.normal(size=(6, N, m))
    a = ukf.unscented_kalman_filter(zs, x[0], P, lambda s: _mv(F, s), 0.1 * np.eye(n), H, R)
    b = ukf.unscented_kalman_filter(zs, x[0], P, lambda s: _mv(F, s), 0.1 * np.eye(n), lambda s: _mv(H, s), R)
    for name, p_, q_ in zip(a._fields, a, b):
        assert np.array_equal(p_, q_, equal_nan=True), name

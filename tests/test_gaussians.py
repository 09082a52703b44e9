"""Tests of kftrack.gaussians: densities, products, the 1-D update, the moment test."""
import math

import numpy as np
import pytest
from filterpy.stats import mul as fp_mul
from filterpy.stats import multivariate_multiply as fp_mvmul
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate, stats

from closed_forms import EPS, roundoff_tol
from kftrack.gaussians import (gaussian_logpdf, gaussian_pdf, moment_test, multiply_gaussians,
                               multiply_multivariate_gaussians, multivariate_gaussian_logpdf,
                               multivariate_gaussian_pdf, update_1d)
from kftrack.kalman import update
from kftrack.metrics import chi2_bounds

# Absolute round-off allowance where results fall below the smallest normal float (gradual underflow:
# relative bounds do not hold there): four times the smallest normal number.
UNDERFLOW = 4 * np.finfo(float).tiny


finite = st.floats(-1e3, 1e3, allow_nan=False)
variance = st.floats(1e-3, 1e3, allow_nan=False)


def _spd(rng, n, batch=()):
    A = rng.standard_normal(batch + (n, n))
    return A @ np.swapaxes(A, -1, -2) + n * np.eye(n)


def _pdf_rtol(arg):
    """Relative round-off of exp(-arg) / sqrt(2 pi var), arg = (x - mu)^2 / (2 var), between two codes:
    arg takes <= 4 roundings (4 u |arg| absolute, which exp turns into relative), exp and the
    normaliser <= 1 + 3 u more: 4 u |arg| + 4 u each way, <= eps (4 |arg| + 5) together."""
    return EPS * (4 * np.abs(arg) + 5)


def _logpdf_atol(arg, var, value):
    """Absolute round-off of -arg - log(2 pi var) / 2 between two codes: 4 u |arg| + 3 u |log term|
    + u |value| (the final sum) each way."""
    return EPS * (4 * np.abs(arg) + 3 * np.abs(0.5 * np.log(2 * np.pi * var)) + np.abs(value))


# --------------------------------------------------------------------------- densities

def test_pdf_matches_scipy_and_takes_a_variance():
    rng = np.random.default_rng(0)
    x, mu, var = rng.normal(size=50), rng.normal(size=50), rng.uniform(0.1, 4, 50)
    arg = (x - mu) ** 2 / (2 * var)
    want = stats.norm.pdf(x, mu, np.sqrt(var))
    assert np.all(np.abs(gaussian_pdf(x, mu, var) - want) <= _pdf_rtol(arg) * want)
    want = stats.norm.logpdf(x, mu, np.sqrt(var))
    assert np.all(np.abs(gaussian_logpdf(x, mu, var) - want) <= _logpdf_atol(arg, var, want))


def test_pdf_integrates_to_one():
    # quad's error estimate (asked for 1e-13 relative), the mass outside +-20 sigma (2 Q(20) ~ 1e-88),
    # and the round-off of the 21-point Gauss-Kronrod sums over its subintervals
    total, err = integrate.quad(lambda x: gaussian_pdf(x, 100.0, 1.0), 80, 120, epsabs=0, epsrel=1e-13, limit=200)
    assert abs(total - 1.0) <= err + 2 * stats.norm.sf(20.0) + roundoff_tol(1.0, 21)


def test_multivariate_pdf_matches_scipy_with_batch_axes():
    rng = np.random.default_rng(1)
    covs = _spd(rng, 3, (4,))
    means = rng.normal(size=(4, 3))
    x = rng.normal(size=(4, 3))
    got = multivariate_gaussian_pdf(x, means, covs)
    assert got.shape == (4,)
    want = [stats.multivariate_normal(means[i], covs[i]).logpdf(x[i]) for i in range(4)]
    # log density: the Mahalanobis term and log det from a factorization (Cholesky here, eigh in
    # scipy) err by <= n cond(cov) eps relative to their magnitudes; the pdf's relative error is
    # the log's absolute error
    cond = max(np.linalg.cond(c) for c in covs)
    tol = roundoff_tol(np.abs(want).max() + 3 * np.log(2 * np.pi) + max(abs(np.linalg.slogdet(c)[1]) for c in covs), 3, cond)
    np.testing.assert_allclose(got, np.exp(want), rtol=tol, atol=0)
    # a shared covariance broadcasts against many points
    pts = rng.normal(size=(7, 3))
    want = stats.multivariate_normal(means[0], covs[0]).logpdf(pts)
    tol = roundoff_tol(np.abs(want).max() + 3 * np.log(2 * np.pi) + abs(np.linalg.slogdet(covs[0])[1]), 3, np.linalg.cond(covs[0]))
    np.testing.assert_allclose(multivariate_gaussian_logpdf(pts, means[0], covs[0]), want, rtol=0, atol=tol)


def test_one_dimensional_multivariate_equals_scalar():
    # arg = 0.0225: _pdf_rtol's bound, about 5 eps
    assert np.isclose(multivariate_gaussian_pdf([1.3], [1.0], [[2.0]]), gaussian_pdf(1.3, 1.0, 2.0), rtol=_pdf_rtol(0.0225), atol=0)


# --------------------------------------------------------------------------- products

def test_product_closed_form_and_filterpy():
    p = multiply_gaussians(10.0, 4.0, 12.0, 1.0)
    # a few (<= 4) roundings of positive terms each way: <= 8 u = 4 eps relative (rtol 10 eps)
    rtol = roundoff_tol(1.0, 1)
    assert np.isclose(p.mean, (1.0 * 10 + 4.0 * 12) / 5.0, rtol=rtol, atol=0) and np.isclose(p.var, 4.0 / 5.0, rtol=rtol, atol=0)
    assert np.isclose(p.scale, stats.norm.pdf(10.0, 12.0, np.sqrt(5.0)), rtol=_pdf_rtol(4.0 / 10.0), atol=0)
    fm, fv = fp_mul(10.0, 4.0, 12.0, 1.0)
    assert np.isclose(p.mean, fm, rtol=rtol, atol=0) and np.isclose(p.var, fv, rtol=rtol, atol=0)


@settings(max_examples=200, deadline=None)
@given(finite, variance, finite, variance, finite)
def test_product_is_pointwise_product_of_densities(m1, v1, m2, v2, x):
    p = multiply_gaussians(m1, v1, m2, v2)
    lhs = gaussian_logpdf(x, m1, v1) + gaussian_logpdf(x, m2, v2)
    rhs = p.log_scale + gaussian_logpdf(x, p.mean, p.var)
    # each of the four log densities errs by _logpdf_atol (the scale's has arg (m1 - m2)^2 / 2(v1 + v2));
    # p.mean and p.var carry <= 4 u relative (dm <= 4 u max|m|, dv <= 4 u v), which move the
    # product's arg by |x - m| dm / v + arg dv / v and its log normaliser by dv / (2 v)
    a1, a2 = (x - m1) ** 2 / (2 * v1), (x - m2) ** 2 / (2 * v2)
    a_p, a_s = (x - p.mean) ** 2 / (2 * p.var), (m1 - m2) ** 2 / (2 * (v1 + v2))
    dm = 2 * EPS * max(abs(m1), abs(m2))
    tol = (_logpdf_atol(a1, v1, lhs) + _logpdf_atol(a2, v2, 0.0) + _logpdf_atol(a_p, p.var, rhs)
           + _logpdf_atol(a_s, v1 + v2, p.log_scale) + abs(x - p.mean) * dm / p.var + (a_p + 0.5) * 2 * EPS)
    assert abs(lhs - rhs) <= tol
    assert p.var <= min(v1, v2) * (1 + 2 * EPS)  # fusing never loses information; v1 v2 / (v1 + v2): 3 u
    # a convex combination, <= 4 u max|m|; below the smallest normal number round-off is absolute
    # (gradual underflow), so a few tiny's are added (hypothesis found means of 2.2e-308)
    slack = roundoff_tol(max(abs(m1), abs(m2)), 1, c=2.0) + UNDERFLOW
    assert min(m1, m2) - slack <= p.mean <= max(m1, m2) + slack


def test_product_with_an_exact_value():
    p = multiply_gaussians(3.0, 0.0, 5.0, 2.0)
    assert p.mean == 3.0 and p.var == 0.0


def test_multivariate_product_equals_information_form_and_filterpy():
    rng = np.random.default_rng(2)
    for _ in range(5):
        c1, c2 = _spd(rng, 3), _spd(rng, 3)
        m1, m2 = rng.normal(size=3), rng.normal(size=3)
        p = multiply_multivariate_gaussians(m1, c1, m2, c2)
        Y = np.linalg.inv(c1) + np.linalg.inv(c2)
        info = np.linalg.inv(Y)
        # the information form inverts c1, c2 (relative errors cond(c_i) n eps) and then Y, which
        # amplifies by cond(Y); the product and filterpy solve with c1 + c2 (cond(c1 + c2))
        k = np.linalg.cond(Y) * (np.linalg.cond(c1) + np.linalg.cond(c2)) + np.linalg.cond(c1 + c2)
        m_scale = np.abs(m1).max() + np.abs(m2).max()
        np.testing.assert_allclose(p.var, info, rtol=0, atol=roundoff_tol(np.abs(c1).max() + np.abs(c2).max(), 2 * 3, k))
        np.testing.assert_allclose(p.mean, info @ (np.linalg.solve(c1, m1) + np.linalg.solve(c2, m2)), rtol=0,
                                   atol=roundoff_tol(m_scale, 2 * 3, k))
        fm, fc = fp_mvmul(m1, c1, m2, c2)
        np.testing.assert_allclose(p.mean, np.ravel(fm), rtol=0, atol=roundoff_tol(m_scale, 2 * 3, k))
        np.testing.assert_allclose(p.var, fc, rtol=0, atol=roundoff_tol(np.abs(c1).max() + np.abs(c2).max(), 2 * 3, k))
        # pointwise: N1(x) N2(x) = scale * N(x; mean, var); each log density errs by n cond eps
        # times its terms' size (Mahalanobis, log det, n log 2 pi), the product's moments by the
        # bounds above, which move its Mahalanobis term by <= 2 |x - m| |V^-1| dm + maha |V^-1| dV
        x = rng.normal(size=(6, 3))
        lhs = multivariate_gaussian_logpdf(x, m1, c1) + multivariate_gaussian_logpdf(x, m2, c2)
        rhs = p.log_scale + multivariate_gaussian_logpdf(x, p.mean, p.var)
        terms = 2 * np.abs(lhs).max() + 2 * np.abs(rhs).max() + 4 * 3 * np.log(2 * np.pi)
        Vinv = np.linalg.norm(np.linalg.inv(p.var), 2)
        dm, dV = roundoff_tol(m_scale, 2 * 3, k), roundoff_tol(np.abs(c1).max() + np.abs(c2).max(), 2 * 3, k)
        d_maha = 2 * np.abs(x - p.mean).max() * 3 * Vinv * dm + np.abs(rhs).max() * 3 * Vinv * dV
        np.testing.assert_allclose(lhs, rhs, rtol=0, atol=roundoff_tol(terms, 3, k) + d_maha)


def test_multivariate_product_broadcasts_and_allows_a_singular_factor():
    rng = np.random.default_rng(3)
    c1 = _spd(rng, 2, (5,))
    m1 = rng.normal(size=(5, 2))
    p = multiply_multivariate_gaussians(m1, c1, np.zeros(2), np.eye(2))
    assert p.mean.shape == (5, 2) and p.var.shape == (5, 2, 2) and p.scale.shape == (5,)
    one = multiply_multivariate_gaussians(m1[2], c1[2], np.zeros(2), np.eye(2))
    # batched and single solves may take different LAPACK paths: a solve with c1 + I, n = 2
    _k = np.linalg.cond(c1[2] + np.eye(2))
    np.testing.assert_allclose(p.mean[2], one.mean, rtol=0, atol=roundoff_tol(m1[2], 2, _k))
    # a singular first factor (x known exactly, y uncertain): the product keeps x exactly. The
    # diagonal system decouples, so the x row is 0 / (0 + 1) and 1 * (1 / 1): exact in floating point
    c_exact_x = np.diag([0.0, 5.0])
    q = multiply_multivariate_gaussians([1.0, 2.0], c_exact_x, [3.0, 4.0], np.eye(2))
    assert q.mean[0] == 1.0 and q.var[0, 0] == 0.0


# --------------------------------------------------------------------------- the 1-D update

@settings(max_examples=200, deadline=None)
@given(finite, variance, finite, variance)
def test_update_1d_is_the_product_and_the_kalman_update(x, P, z, R):
    u = update_1d(x, P, z, R)
    p = multiply_gaussians(x, P, z, R)
    # x + K (z - x) and (R x + P z) / (P + R): <= 4 roundings of terms <= max(|x|, |z|) each way;
    # P R / (P + R): 3 u relative each way, rtol 10 eps
    m = max(abs(x), abs(z))
    assert np.isclose(u.x, p.mean, rtol=0, atol=roundoff_tol(m, 1) + UNDERFLOW) and np.isclose(u.P, p.var, rtol=roundoff_tol(1.0, 1), atol=0)
    k = update([x], [[P]], [z], [[1.0]], [[R]])
    # Joseph (1 - K)^2 P + K^2 R: 1 - K loses u K / (1 - K) = u P / R relative, but its term is
    # (1 - K)^2 P = P_post R / (P + R), so the absolute loss is <= 2 u P_post: a few u relative in all
    assert np.isclose(u.x, k.x[0], rtol=0, atol=roundoff_tol(m, 1)) and np.isclose(u.P, k.P[0, 0], rtol=roundoff_tol(1.0, 1), atol=0)
    arg = (z - x) ** 2 / (2 * (P + R))
    ll = gaussian_logpdf(z, x, P + R)
    assert np.isclose(u.loglik, ll, rtol=0, atol=2 * _logpdf_atol(arg, P + R, ll))
    assert np.isclose(u.K, P / (P + R), rtol=2 * EPS, atol=0)  # two roundings each way: <= 4 u


def test_update_1d_sequential_equals_batch_average():
    """n updates with equal R from a flat-ish prior give the weighted mean and R/n-like variance."""
    rng = np.random.default_rng(4)
    z = 100 + rng.standard_normal(50)
    x, P = 0.0, 1e6
    for zk in z:
        u = update_1d(x, P, zk, 1.0)
        x, P = u.x, u.P
    info = 1 / 1e6 + 50 / 1.0
    # each update P R / (P + R) adds <= 3 u relative and does not amplify earlier relative errors
    # (d P_post / P_post = R / (P + R) dP / P); x moves by <= 4 u |z| per step, damped the same way;
    # the reference sums 50 terms (50 u): 50 steps, rtol = roundoff_tol(1, 50) = 500 eps
    assert np.isclose(P, 1 / info, rtol=roundoff_tol(1.0, 50), atol=0)
    assert np.isclose(x, (0.0 / 1e6 + z.sum()) / info, rtol=roundoff_tol(1.0, 50), atol=0)


def test_update_1d_is_calibrated_monte_carlo():
    """Posterior errors normalised by the posterior variance are chi-square(1) on average."""
    rng = np.random.default_rng(5)
    runs = 20_000
    x0, P0, R = 10.0, 4.0, 1.0
    truth = x0 + np.sqrt(P0) * rng.standard_normal(runs)
    z = truth + np.sqrt(R) * rng.standard_normal(runs)
    u = update_1d(x0, P0, z, R)  # broadcasts over the runs
    nees = (u.x - truth) ** 2 / u.P
    lo, hi = chi2_bounds(1, runs, 0.99)
    assert lo <= nees.mean() <= hi


def test_update_1d_with_zero_prior_variance_ignores_the_measurement():
    u = update_1d(5.0, 0.0, 9.0, 1.0)
    assert u.x == 5.0 and u.P == 0.0


# --------------------------------------------------------------------------- the moment test

def test_moment_test_false_alarm_rate_is_alpha():
    rng = np.random.default_rng(6)
    trials, alpha = 400, 0.05
    rejections = sum(not (r.mean_ok and r.var_ok)
                     for r in (moment_test(3 + 2 * rng.standard_normal(200), 3.0, 4.0, 1 - alpha)
                               for _ in range(trials)))
    # two nearly independent tests at alpha each: P(reject) = 1 - (1 - alpha)^2
    p = 1 - (1 - alpha) ** 2
    lo, hi = stats.binom.ppf([0.001, 0.999], trials, p)
    assert lo <= rejections <= hi


def test_moment_test_detects_a_wrong_variance_and_a_wrong_mean():
    rng = np.random.default_rng(7)
    x = rng.standard_normal(2000)
    assert not moment_test(x, 0.0, 1.3).var_ok
    assert not moment_test(x + 0.2, 0.0, 1.0).mean_ok
    r = moment_test(x, 0.0, 1.0)
    assert r.mean_ok and r.var_ok and r.n == 2000


# --------------------------------------------------------------------------- bad input

@pytest.mark.parametrize("call, name", [
    (lambda: gaussian_pdf(0.0, 0.0, -1.0), "var"),
    (lambda: gaussian_pdf(np.nan, 0.0, 1.0), "x"),
    (lambda: multiply_gaussians(0.0, -1.0, 0.0, 1.0), "var1"),
    (lambda: multiply_gaussians(0.0, 0.0, 1.0, 0.0), "var1 + var2"),
    (lambda: multivariate_gaussian_pdf([0.0, 0.0], [0.0], np.eye(2)), "mean"),
    (lambda: multivariate_gaussian_pdf([0.0, 0.0], [0.0, 0.0], [[1.0, 2.0], [0.0, 1.0]]), "cov"),
    (lambda: multivariate_gaussian_pdf([0.0, 0.0], [0.0, 0.0], np.zeros((2, 2))), "cov"),
    (lambda: multiply_multivariate_gaussians([0, 0], np.eye(2), [0, 0, 0], np.eye(3)), "mean2"),
    (lambda: multiply_multivariate_gaussians([0, 0], np.zeros((2, 2)), [0, 0], np.zeros((2, 2))), "cov1 + cov2"),
    (lambda: update_1d(0.0, 1.0, 0.0, 0.0), "R"),
    (lambda: update_1d(0.0, -1.0, 0.0, 1.0), "P"),
    (lambda: moment_test([1.0], 0.0, 1.0), "sample"),
    (lambda: moment_test([1.0, 2.0], 0.0, 0.0), "var"),
    (lambda: moment_test([1.0, 2.0], 0.0, 1.0, 1.5), "confidence"),
])
def test_bad_input_names_the_argument(call, name):
    with pytest.raises(ValueError, match=name.replace("+", r"\+")):
        call()


def test_mahalanobis_and_ellipse_mass():
    from kftrack.gaussians import ellipse_mass, mahalanobis2
    cov = np.array([[4.0, 1.0], [1.0, 2.0]])
    x, mu = np.array([1.0, -2.0]), np.array([0.5, 0.5])
    d = x - mu
    # 2x2 SPD solve: relative error <= n cond(cov) eps each way (cond ~ 2.6)
    assert np.isclose(mahalanobis2(x, mu, cov), d @ np.linalg.solve(cov, d), rtol=roundoff_tol(1.0, 2, np.linalg.cond(cov)), atol=0)
    # chi2 cdf and 1 - exp(-2) = 0.86 (no cancellation): a few ulp each
    assert np.isclose(ellipse_mass(2.0, 2), 1 - np.exp(-2.0), rtol=roundoff_tol(1.0, 2), atol=0)
    # the 1-D mass is erf(k / sqrt 2) to round-off; 0.95 belongs to the exact quantile z = 1.95996...,
    # and the mass at 1.96 exceeds it by at most 2 phi(z) (1.96 - z) (mean value theorem, phi falling)
    assert np.isclose(ellipse_mass(1.96, 1), math.erf(1.96 / math.sqrt(2)), rtol=roundoff_tol(1.0, 2), atol=0)
    z = stats.norm.isf(0.025)
    assert 0 <= ellipse_mass(1.96, 1) - 0.95 <= 2 * stats.norm.pdf(z) * (1.96 - z) + roundoff_tol(1.0, 2)
    with pytest.raises(ValueError, match="nsigma"):
        ellipse_mass(-1.0)
    with pytest.raises(ValueError, match="dim"):
        ellipse_mass(2.0, 0)


def test_ellipse_mass_monte_carlo():
    # binomial bound, two-sided 99.9 %: the fraction of 2-D Gaussian draws inside the 2-sigma ellipse
    from kftrack.gaussians import ellipse_mass, mahalanobis2
    rng = np.random.default_rng(7)
    cov = np.array([[4.0, 1.5], [1.5, 1.0]])
    n = 20000
    x = rng.multivariate_normal([1.0, 2.0], cov, size=n)
    inside = int(np.sum(mahalanobis2(x, [1.0, 2.0], cov) <= 4.0))
    p = float(ellipse_mass(2.0, 2))
    lo, hi = stats.binom.ppf([0.0005, 0.9995], n, p)
    assert lo <= inside <= hi


def test_allan_deviation_white_noise_law():
    # white rate noise: E[avar] = sigma^2 / m exactly; edf * avar / E ~ chi2(edf) (two-moment
    # approximation); test every tau at a Bonferroni two-sided 99.9 % level, and check the
    # exact mean with many replicates (normal bound on the mean of 400 Allan variances)
    from kftrack.gaussians import allan_deviation
    rng = np.random.default_rng(11)
    sigma, dt = 0.03, 0.01
    y = sigma * rng.standard_normal(100_000)
    ms = np.array([1, 4, 16, 64, 256, 1024])
    ad = allan_deviation(y, dt, ms)
    np.testing.assert_allclose(ad.tau, ms * dt, rtol=EPS, atol=0)  # one product each way: <= 2 u
    expected = sigma**2 / ms  # = N^2 / tau with N^2 = sigma^2 dt
    stat = ad.edf * ad.adev**2 / expected
    a = 0.001 / ms.size
    assert np.all(stats.chi2.ppf(a / 2, ad.edf) <= stat) and np.all(stat <= stats.chi2.ppf(1 - a / 2, ad.edf))
    reps = np.array([allan_deviation(sigma * rng.standard_normal(64), dt, 8).adev[0] ** 2 for _ in range(400)])
    se = reps.std(ddof=1) / np.sqrt(reps.size)
    # two-sided at level 1e-3, the standard error estimated from the 400 replicates: Student t, 399 dof
    assert abs(reps.mean() - sigma**2 / 8) <= stats.t.isf(0.0005, reps.size - 1) * se


def test_allan_deviation_rejects_bad_input():
    from kftrack.gaussians import allan_deviation
    with pytest.raises(ValueError, match="m must"):
        allan_deviation(np.ones(10), 0.1, 6)
    with pytest.raises(ValueError, match="dt"):
        allan_deviation(np.ones(10), 0.0, 2)
    with pytest.raises(ValueError, match="m must"):
        allan_deviation(np.ones(10), 0.1, 1.5)

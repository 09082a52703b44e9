"""Tests of kftrack.gaussians: densities, products, the 1-D update, the moment test."""
import numpy as np
import pytest
from filterpy.stats import mul as fp_mul
from filterpy.stats import multivariate_multiply as fp_mvmul
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate, stats

from kftrack.gaussians import (gaussian_logpdf, gaussian_pdf, moment_test, multiply_gaussians,
                               multiply_multivariate_gaussians, multivariate_gaussian_logpdf,
                               multivariate_gaussian_pdf, update_1d)
from kftrack.kalman import update
from kftrack.metrics import chi2_bounds

finite = st.floats(-1e3, 1e3, allow_nan=False)
variance = st.floats(1e-3, 1e3, allow_nan=False)


def _spd(rng, n, batch=()):
    A = rng.standard_normal(batch + (n, n))
    return A @ np.swapaxes(A, -1, -2) + n * np.eye(n)


# --------------------------------------------------------------------------- densities

def test_pdf_matches_scipy_and_takes_a_variance():
    rng = np.random.default_rng(0)
    x, mu, var = rng.normal(size=50), rng.normal(size=50), rng.uniform(0.1, 4, 50)
    np.testing.assert_allclose(gaussian_pdf(x, mu, var), stats.norm.pdf(x, mu, np.sqrt(var)), rtol=1e-13)
    np.testing.assert_allclose(gaussian_logpdf(x, mu, var), stats.norm.logpdf(x, mu, np.sqrt(var)), rtol=1e-13)


def test_pdf_integrates_to_one():
    total, _ = integrate.quad(lambda x: gaussian_pdf(x, 100.0, 1.0), 80, 120)
    assert abs(total - 1.0) < 1e-10


def test_multivariate_pdf_matches_scipy_with_batch_axes():
    rng = np.random.default_rng(1)
    covs = _spd(rng, 3, (4,))
    means = rng.normal(size=(4, 3))
    x = rng.normal(size=(4, 3))
    got = multivariate_gaussian_pdf(x, means, covs)
    assert got.shape == (4,)
    want = [stats.multivariate_normal(means[i], covs[i]).pdf(x[i]) for i in range(4)]
    np.testing.assert_allclose(got, want, rtol=1e-12)
    # a shared covariance broadcasts against many points
    pts = rng.normal(size=(7, 3))
    np.testing.assert_allclose(multivariate_gaussian_logpdf(pts, means[0], covs[0]),
                               stats.multivariate_normal(means[0], covs[0]).logpdf(pts), rtol=1e-12)


def test_one_dimensional_multivariate_equals_scalar():
    assert np.isclose(multivariate_gaussian_pdf([1.3], [1.0], [[2.0]]), gaussian_pdf(1.3, 1.0, 2.0), rtol=1e-14)


# --------------------------------------------------------------------------- products

def test_product_closed_form_and_filterpy():
    p = multiply_gaussians(10.0, 4.0, 12.0, 1.0)
    assert np.isclose(p.mean, (1.0 * 10 + 4.0 * 12) / 5.0) and np.isclose(p.var, 4.0 / 5.0)
    assert np.isclose(p.scale, stats.norm.pdf(10.0, 12.0, np.sqrt(5.0)))
    fm, fv = fp_mul(10.0, 4.0, 12.0, 1.0)
    assert np.isclose(p.mean, fm) and np.isclose(p.var, fv)


@settings(max_examples=200, deadline=None)
@given(finite, variance, finite, variance, finite)
def test_product_is_pointwise_product_of_densities(m1, v1, m2, v2, x):
    p = multiply_gaussians(m1, v1, m2, v2)
    lhs = gaussian_logpdf(x, m1, v1) + gaussian_logpdf(x, m2, v2)
    rhs = p.log_scale + gaussian_logpdf(x, p.mean, p.var)
    assert np.isclose(lhs, rhs, rtol=1e-9, atol=1e-9)
    assert p.var <= min(v1, v2) * (1 + 1e-12)          # fusing never loses information
    assert min(m1, m2) - 1e-9 <= p.mean <= max(m1, m2) + 1e-9


def test_product_with_an_exact_value():
    p = multiply_gaussians(3.0, 0.0, 5.0, 2.0)
    assert p.mean == 3.0 and p.var == 0.0


def test_multivariate_product_equals_information_form_and_filterpy():
    rng = np.random.default_rng(2)
    for _ in range(5):
        c1, c2 = _spd(rng, 3), _spd(rng, 3)
        m1, m2 = rng.normal(size=3), rng.normal(size=3)
        p = multiply_multivariate_gaussians(m1, c1, m2, c2)
        info = np.linalg.inv(np.linalg.inv(c1) + np.linalg.inv(c2))
        np.testing.assert_allclose(p.var, info, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(p.mean, info @ (np.linalg.solve(c1, m1) + np.linalg.solve(c2, m2)), rtol=1e-10)
        fm, fc = fp_mvmul(m1, c1, m2, c2)
        np.testing.assert_allclose(p.mean, np.ravel(fm), rtol=1e-10)
        np.testing.assert_allclose(p.var, fc, rtol=1e-10)
        # pointwise: N1(x) N2(x) = scale * N(x; mean, var)
        x = rng.normal(size=(6, 3))
        lhs = multivariate_gaussian_logpdf(x, m1, c1) + multivariate_gaussian_logpdf(x, m2, c2)
        rhs = p.log_scale + multivariate_gaussian_logpdf(x, p.mean, p.var)
        np.testing.assert_allclose(lhs, rhs, rtol=1e-10)


def test_multivariate_product_broadcasts_and_allows_a_singular_factor():
    rng = np.random.default_rng(3)
    c1 = _spd(rng, 2, (5,))
    m1 = rng.normal(size=(5, 2))
    p = multiply_multivariate_gaussians(m1, c1, np.zeros(2), np.eye(2))
    assert p.mean.shape == (5, 2) and p.var.shape == (5, 2, 2) and p.scale.shape == (5,)
    one = multiply_multivariate_gaussians(m1[2], c1[2], np.zeros(2), np.eye(2))
    np.testing.assert_allclose(p.mean[2], one.mean, rtol=1e-13)
    # a singular first factor (x known exactly, y uncertain): the product keeps x exactly
    c_exact_x = np.diag([0.0, 5.0])
    q = multiply_multivariate_gaussians([1.0, 2.0], c_exact_x, [3.0, 4.0], np.eye(2))
    assert np.isclose(q.mean[0], 1.0) and np.isclose(q.var[0, 0], 0.0, atol=1e-15)


# --------------------------------------------------------------------------- the 1-D update

@settings(max_examples=200, deadline=None)
@given(finite, variance, finite, variance)
def test_update_1d_is_the_product_and_the_kalman_update(x, P, z, R):
    u = update_1d(x, P, z, R)
    p = multiply_gaussians(x, P, z, R)
    assert np.isclose(u.x, p.mean, rtol=1e-12, atol=1e-9) and np.isclose(u.P, p.var, rtol=1e-12)
    k = update([x], [[P]], [z], [[1.0]], [[R]])
    assert np.isclose(u.x, k.x[0], rtol=1e-10, atol=1e-9) and np.isclose(u.P, k.P[0, 0], rtol=1e-9)
    assert np.isclose(u.loglik, gaussian_logpdf(z, x, P + R), rtol=1e-10, atol=1e-10)
    assert np.isclose(u.K, P / (P + R))


def test_update_1d_sequential_equals_batch_average():
    """n updates with equal R from a flat-ish prior give the weighted mean and R/n-like variance."""
    rng = np.random.default_rng(4)
    z = 100 + rng.standard_normal(50)
    x, P = 0.0, 1e6
    for zk in z:
        u = update_1d(x, P, zk, 1.0)
        x, P = u.x, u.P
    info = 1 / 1e6 + 50 / 1.0
    assert np.isclose(P, 1 / info, rtol=1e-12)
    assert np.isclose(x, (0.0 / 1e6 + z.sum()) / info, rtol=1e-12)


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
    # 2x2 SPD solve: relative error a few eps times cond(cov) ~ 3
    assert np.isclose(mahalanobis2(x, mu, cov), d @ np.linalg.solve(cov, d), rtol=1e-13)
    assert np.isclose(ellipse_mass(2.0, 2), 1 - np.exp(-2.0), rtol=1e-14)
    assert np.isclose(ellipse_mass(1.96, 1), 0.95, atol=5e-5)
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
    np.testing.assert_allclose(ad.tau, ms * dt)
    expected = sigma**2 / ms  # = N^2 / tau with N^2 = sigma^2 dt
    stat = ad.edf * ad.adev**2 / expected
    a = 0.001 / ms.size
    assert np.all(stats.chi2.ppf(a / 2, ad.edf) <= stat) and np.all(stat <= stats.chi2.ppf(1 - a / 2, ad.edf))
    reps = np.array([allan_deviation(sigma * rng.standard_normal(64), dt, 8).adev[0] ** 2 for _ in range(400)])
    se = reps.std(ddof=1) / np.sqrt(reps.size)
    assert abs(reps.mean() - sigma**2 / 8) <= stats.norm.ppf(1 - 0.0005) * se


def test_allan_deviation_rejects_bad_input():
    from kftrack.gaussians import allan_deviation
    with pytest.raises(ValueError, match="m must"):
        allan_deviation(np.ones(10), 0.1, 6)
    with pytest.raises(ValueError, match="dt"):
        allan_deviation(np.ones(10), 0.0, 2)
    with pytest.raises(ValueError, match="m must"):
        allan_deviation(np.ones(10), 0.1, 1.5)

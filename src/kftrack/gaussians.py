r"""Gaussians: densities, products, the 1-D measurement update, and sample-moment checks.

Numerics layer: pure functions, no plotting, no I/O. Everything broadcasts over leading
batch axes: scalars for the 1-D functions, ``(..., n)`` means and ``(..., n, n)``
covariances for the multivariate ones.

The product of two Gaussian densities is an unnormalised Gaussian (Bar-Shalom, Li &
Kirubarajan 2001, §1.4; Särkkä 2013, App. A.1):

.. math::

    \mathcal N(x; \mu_1, \Sigma_1)\,\mathcal N(x; \mu_2, \Sigma_2)
    = \mathcal N(\mu_1; \mu_2, \Sigma_1 + \Sigma_2)\;\mathcal N(x; \mu, \Sigma),

    \Sigma = \Sigma_1 - \Sigma_1 (\Sigma_1 + \Sigma_2)^{-1} \Sigma_1
           = (\Sigma_1^{-1} + \Sigma_2^{-1})^{-1},
    \qquad
    \mu = \mu_1 + \Sigma_1 (\Sigma_1 + \Sigma_2)^{-1} (\mu_2 - \mu_1).

With a prior :math:`\mathcal N(x; \hat x, P)` and a direct measurement :math:`z = x + v`,
:math:`v \sim \mathcal N(0, R)`, the posterior is that product: the 1-D Kalman update
(:func:`update_1d`).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import stats

from ._validate import as_float_array, as_vector, check_covariance, check_finite
from .kalman import Update

__all__ = [
    "GaussianProduct",
    "MomentTest",
    "gaussian_pdf",
    "gaussian_logpdf",
    "multivariate_gaussian_pdf",
    "multivariate_gaussian_logpdf",
    "multiply_gaussians",
    "multiply_multivariate_gaussians",
    "update_1d",
    "moment_test",
    "mahalanobis2",
    "ellipse_mass",
    "AllanDeviation",
    "allan_deviation",
]

_LOG_2PI = np.log(2.0 * np.pi)


class GaussianProduct(NamedTuple):
    """Product of two Gaussian densities, ``scale * N(x; mean, var)``.

    Attributes
    ----------
    mean : (...) or (..., n) mean of the normalised product.
    var : (...) variance, or (..., n, n) covariance, of the normalised product.
    scale : (...) the normalising constant ``N(mean1; mean2, var1 + var2)``: the likelihood
        of one Gaussian's mean under the other, widened by both variances.
    log_scale : (...) its logarithm (use it when the means are many sigmas apart: ``scale``
        underflows, ``log_scale`` does not).
    """

    mean: np.ndarray
    var: np.ndarray
    scale: np.ndarray
    log_scale: np.ndarray


class MomentTest(NamedTuple):
    """Result of :func:`moment_test`: do a sample's mean and variance fit N(mean, var)?

    Attributes
    ----------
    n : number of samples.
    sample_mean, sample_var : the sample mean and the unbiased sample variance (ddof=1).
    t : Student t statistic ``(sample_mean - mean) / (s / sqrt(n))``.
    t_crit : two-sided critical value of t with ``n - 1`` degrees of freedom.
    chi2 : ``(n - 1) * sample_var / var``, chi-square with ``n - 1`` degrees of freedom.
    chi2_lo, chi2_hi : its two-sided acceptance interval.
    mean_ok, var_ok : whether each statistic lies inside its interval.
    """

    n: int
    sample_mean: float
    sample_var: float
    t: float
    t_crit: float
    chi2: float
    chi2_lo: float
    chi2_hi: float
    mean_ok: bool
    var_ok: bool


def _positive(value, name: str) -> np.ndarray:
    arr = check_finite(as_float_array(value, name), name)
    if np.any(arr <= 0.0):
        raise ValueError(f"{name} must be a positive variance, got min {arr.min()!r}")
    return arr


def _nonnegative(value, name: str) -> np.ndarray:
    arr = check_finite(as_float_array(value, name), name)
    if np.any(arr < 0.0):
        raise ValueError(f"{name} must be a non-negative variance, got min {arr.min()!r}")
    return arr


def gaussian_logpdf(x, mean, var) -> np.ndarray:
    r"""Log-density of the 1-D Gaussian, :math:`-\tfrac12[\log 2\pi\sigma^2 + (x-\mu)^2/\sigma^2]`.

    Parameters
    ----------
    x, mean : array_like, broadcast together.
    var : array_like, the variance :math:`\sigma^2 > 0` (not the standard deviation).
    """
    x = check_finite(as_float_array(x, "x"), "x")
    mean = check_finite(as_float_array(mean, "mean"), "mean")
    var = _positive(var, "var")
    return -0.5 * (_LOG_2PI + np.log(var) + (x - mean) ** 2 / var)


def gaussian_pdf(x, mean, var) -> np.ndarray:
    r"""Density of the 1-D Gaussian :math:`\mathcal N(x; \mu, \sigma^2)`.

    ``var`` is the variance :math:`\sigma^2 > 0`; ``x``, ``mean`` and ``var`` broadcast.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.gaussians import gaussian_pdf
    >>> print(np.round(gaussian_pdf([0.0, 1.0, 2.0], 0.0, 4.0), 6))   # N(x; 0, 4): var, not sigma
    [0.199471 0.176033 0.120985]
    """
    return np.exp(gaussian_logpdf(x, mean, var))


def multivariate_gaussian_logpdf(x, mean, cov) -> np.ndarray:
    r"""Log-density of :math:`\mathcal N(x; \mu, \Sigma)` in ``n`` dimensions.

    .. math:: -\tfrac12\left[n \log 2\pi + \log\det\Sigma + (x-\mu)^\top\Sigma^{-1}(x-\mu)\right]

    Parameters
    ----------
    x : (..., n) points.
    mean : (..., n) mean, broadcast against ``x``.
    cov : (n, n) or (..., n, n) covariance, symmetric positive definite.

    Returns
    -------
    (...) log-densities.
    """
    x = as_vector(x, "x")
    n = x.shape[-1]
    mean = as_vector(mean, "mean", n)
    cov = check_covariance(cov, "cov", n, positive_definite=True)
    L = np.linalg.cholesky(cov)
    e = np.broadcast_to(x - mean, np.broadcast_shapes((x - mean).shape, cov.shape[:-1]))
    L = np.broadcast_to(L, e.shape[:-1] + (n, n))
    w = np.linalg.solve(L, e[..., None])[..., 0]
    logdet = 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)
    return -0.5 * (n * _LOG_2PI + logdet + np.sum(w * w, axis=-1))


def multivariate_gaussian_pdf(x, mean, cov) -> np.ndarray:
    r"""Density of :math:`\mathcal N(x; \mu, \Sigma)`; shapes as in :func:`multivariate_gaussian_logpdf`."""
    return np.exp(multivariate_gaussian_logpdf(x, mean, cov))


def multiply_gaussians(mean1, var1, mean2, var2) -> GaussianProduct:
    r"""Product of two 1-D Gaussian densities (module docstring for the equations).

    .. math::

        \mu = \frac{\sigma_2^2 \mu_1 + \sigma_1^2 \mu_2}{\sigma_1^2 + \sigma_2^2},
        \qquad
        \sigma^2 = \frac{\sigma_1^2 \sigma_2^2}{\sigma_1^2 + \sigma_2^2}

    Either variance may be zero (a known value), not both. All arguments broadcast.

    Returns
    -------
    GaussianProduct
        ``(mean, var, scale, log_scale)`` with ``scale = N(mean1; mean2, var1 + var2)``.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.gaussians import multiply_gaussians
    >>> p = multiply_gaussians(0.0, 4.0, 10.0, 1.0)   # N(0, 4) times N(10, 1)
    >>> print(np.round([p.mean, p.var], 6))           # pulled towards the narrower one
    [8.  0.8]
    """
    mean1 = check_finite(as_float_array(mean1, "mean1"), "mean1")
    mean2 = check_finite(as_float_array(mean2, "mean2"), "mean2")
    var1 = _nonnegative(var1, "var1")
    var2 = _nonnegative(var2, "var2")
    total = var1 + var2
    if np.any(total <= 0.0):
        raise ValueError("var1 + var2 must be positive: two exact values cannot be multiplied")
    mean = (var2 * mean1 + var1 * mean2) / total
    var = var1 * var2 / total
    log_scale = -0.5 * (_LOG_2PI + np.log(total) + (mean1 - mean2) ** 2 / total)
    return GaussianProduct(mean, var, np.exp(log_scale), log_scale)


def multiply_multivariate_gaussians(mean1, cov1, mean2, cov2) -> GaussianProduct:
    r"""Product of two Gaussian densities in ``n`` dimensions, in the gain form

    .. math::

        K = \Sigma_1(\Sigma_1 + \Sigma_2)^{-1}, \quad \mu = \mu_1 + K(\mu_2 - \mu_1),
        \quad \Sigma = (I - K)\Sigma_1,

    which needs only :math:`\Sigma_1 + \Sigma_2` to be invertible (either factor may be
    singular) and equals the information form :math:`(\Sigma_1^{-1}+\Sigma_2^{-1})^{-1}`.

    Parameters
    ----------
    mean1, mean2 : (..., n) means.
    cov1, cov2 : (..., n, n) covariances, symmetric positive semi-definite, with a positive
        definite sum.

    Returns
    -------
    GaussianProduct
        ``mean (..., n)``, ``var (..., n, n)`` (the covariance, symmetrised) and
        ``scale (...) = N(mean1; mean2, cov1 + cov2)`` and ``log_scale``.
    """
    mean1 = as_vector(mean1, "mean1")
    n = mean1.shape[-1]
    mean2 = as_vector(mean2, "mean2", n)
    cov1 = check_covariance(cov1, "cov1", n)
    cov2 = check_covariance(cov2, "cov2", n)
    total = cov1 + cov2
    check_covariance(total, "cov1 + cov2", n, positive_definite=True)
    d = mean2 - mean1
    shape = np.broadcast_shapes(d.shape, total.shape[:-1], cov1.shape[:-1])
    d = np.broadcast_to(d, shape)
    total_b = np.broadcast_to(total, shape[:-1] + (n, n))
    cov1_b = np.broadcast_to(cov1, shape[:-1] + (n, n))
    # K^T = total^{-1} cov1 (both symmetric)
    Kt = np.linalg.solve(total_b, cov1_b)
    K = np.swapaxes(Kt, -1, -2)
    mean = mean1 + np.einsum("...ij,...j->...i", K, d)
    cov = cov1_b - K @ cov1_b
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    log_scale = multivariate_gaussian_logpdf(mean1, mean2, total)
    return GaussianProduct(mean, cov, np.exp(log_scale), log_scale)


def update_1d(x, P, z, R) -> Update:
    r"""The 1-D measurement update: prior :math:`\mathcal N(\hat x, P)`, measurement
    :math:`z = x + v`, :math:`v\sim\mathcal N(0, R)`.

    .. math::

        y = z - \hat x,\quad S = P + R,\quad K = P/S,\quad
        \hat x^+ = \hat x + K y,\quad P^+ = (1-K)P = \frac{PR}{P+R}

    The posterior is the normalised product of the prior and the likelihood
    (:func:`multiply_gaussians`); it is :func:`kftrack.kalman.update` with ``H = [[1]]``.

    Parameters
    ----------
    x, P : prior mean and variance (``P >= 0``), array_like, broadcast together.
    z : measurement(s); ``R`` its noise variance, ``R > 0``.

    Returns
    -------
    kftrack.kalman.Update
        ``(x, P, y, S, K, nis, loglik)`` with scalar (batch-shaped) fields.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.gaussians import update_1d
    >>> u = update_1d(0.0, 4.0, 10.0, 1.0)            # prior N(0, 4), measurement 10 with variance 1
    >>> print(np.round([u.x, u.P, u.K, u.nis], 6))    # the same numbers as multiply_gaussians
    [ 8.   0.8  0.8 20. ]
    """
    x = check_finite(as_float_array(x, "x"), "x")
    P = _nonnegative(P, "P")
    z = check_finite(as_float_array(z, "z"), "z")
    R = _positive(R, "R")
    y = z - x
    S = P + R
    K = P / S
    x_post = x + K * y
    P_post = P * R / S
    nis = y * y / S
    loglik = -0.5 * (nis + np.log(S) + _LOG_2PI)
    return Update(x_post, P_post, y, S, K, nis, loglik)


def moment_test(sample, mean: float, var: float, confidence: float = 0.95) -> MomentTest:
    r"""Test whether a sample's mean and variance are consistent with :math:`\mathcal N(\mu, \sigma^2)`.

    For ``n`` independent Gaussian samples,

    .. math::

        t = \frac{\bar x - \mu}{s/\sqrt n} \sim t_{n-1}, \qquad
        \frac{(n-1)s^2}{\sigma^2} \sim \chi^2_{n-1},

    and each statistic is accepted inside its central interval of probability
    ``confidence``. When several channels are tested together, pass a Bonferroni-corrected
    ``confidence`` (``1 - alpha / checks``) so the whole family holds at ``1 - alpha``.

    Parameters
    ----------
    sample : (n,) finite values, ``n >= 2``.
    mean, var : the model mean and variance (``var > 0``).
    confidence : probability of each acceptance interval, in (0, 1).

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.gaussians import moment_test
    >>> rng = np.random.default_rng(0)
    >>> t = moment_test(rng.normal(1.0, 2.0, 500), mean=1.0, var=4.0)
    >>> t.n, bool(t.mean_ok), bool(t.var_ok)
    (500, True, True)
    >>> bool(moment_test(rng.normal(1.0, 3.0, 500), mean=1.0, var=4.0).var_ok)   # variance 9, not 4
    False
    """
    x = as_vector(sample, "sample")
    if x.ndim != 1 or x.size < 2:
        raise ValueError(f"sample must have shape (n,) with n >= 2, got shape {x.shape}")
    if not np.isfinite(mean):
        raise ValueError(f"mean must be finite, got {mean!r}")
    if not (np.isfinite(var) and var > 0):
        raise ValueError(f"var must be a positive variance, got {var!r}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence!r}")
    n = x.size
    m = float(np.mean(x))
    s2 = float(np.var(x, ddof=1))
    alpha = 1.0 - confidence
    t = (m - mean) / np.sqrt(s2 / n) if s2 > 0 else (0.0 if m == mean else np.inf)
    t_crit = float(stats.t.ppf(1.0 - alpha / 2, n - 1))
    chi2 = (n - 1) * s2 / var
    lo = float(stats.chi2.ppf(alpha / 2, n - 1))
    hi = float(stats.chi2.ppf(1.0 - alpha / 2, n - 1))
    return MomentTest(n, m, s2, float(t), t_crit, float(chi2), lo, hi,
                      bool(abs(t) <= t_crit), bool(lo <= chi2 <= hi))


def mahalanobis2(x, mean, cov) -> np.ndarray:
    r"""Squared Mahalanobis distance :math:`d^2 = (x - \mu)^\top \Sigma^{-1} (x - \mu)`.

    ``x`` and ``mean`` have shape ``(..., n)``, ``cov`` ``(..., n, n)`` (symmetric positive
    definite); broadcasts, returns shape ``(...)``. If :math:`x \sim \mathcal N(\mu, \Sigma)`
    then :math:`d^2 \sim \chi^2_n`.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.gaussians import mahalanobis2
    >>> print(np.round(mahalanobis2([1.0, 2.0], [0.0, 0.0], np.diag([1.0, 4.0])), 6))
    2.0
    """
    x = as_vector(x, "x")
    mean = as_vector(mean, "mean", x.shape[-1])
    cov = check_covariance(cov, "cov", x.shape[-1])
    d = x - mean
    L = np.linalg.cholesky(cov)
    u = np.linalg.solve(L, d[..., None])[..., 0]
    return np.sum(u**2, axis=-1)


def ellipse_mass(nsigma, dim: int = 2) -> np.ndarray:
    r"""Probability mass inside the ``nsigma``-sigma ellipsoid :math:`d^2 \le n_\sigma^2` of an
    ``dim``-dimensional Gaussian: :math:`P(\chi^2_{dim} \le n_\sigma^2)`.

    In one dimension this is the familiar 68 / 95.4 / 99.7 % of ±1, 2, 3 σ; in two dimensions
    it is :math:`1 - e^{-n_\sigma^2/2}`, only 86.5 % for the 2σ ellipse.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.gaussians import ellipse_mass
    >>> print(np.round(ellipse_mass([1, 2, 3], dim=2), 6))   # probability inside the 1, 2, 3 sigma ellipses
    [0.393469 0.864665 0.988891]
    """
    k = as_float_array(nsigma, "nsigma")
    if np.any(~(k >= 0)):
        raise ValueError(f"nsigma must be >= 0, got {nsigma!r}")
    if not (isinstance(dim, (int, np.integer)) and dim >= 1):
        raise ValueError(f"dim must be a positive integer, got {dim!r}")
    return stats.chi2.cdf(k**2, dim)


class AllanDeviation(NamedTuple):
    """Result of :func:`allan_deviation`: cluster times ``tau`` (s), deviations ``adev``
    (units of the signal), number of clusters ``K`` and the equivalent chi-square degrees of
    freedom ``edf`` of each Allan variance (white-noise case)."""

    tau: np.ndarray
    adev: np.ndarray
    K: np.ndarray
    edf: np.ndarray


def allan_deviation(y, dt: float, m) -> AllanDeviation:
    r"""Non-overlapping Allan deviation of a rate signal sampled every ``dt`` seconds.

    For a cluster of ``m`` samples, :math:`\tau = m\,\Delta t`; the ``K = floor(N/m)`` cluster
    means :math:`\bar y_j` give

    .. math:: \sigma_A^2(\tau) = \frac{1}{2(K-1)}\sum_{j=1}^{K-1}(\bar y_{j+1} - \bar y_j)^2 .

    For white noise of per-sample variance :math:`\sigma^2` (noise density
    :math:`N^2 = \sigma^2\Delta t`, the angle random walk of a gyro),
    :math:`E[\sigma_A^2(\tau)] = \sigma^2/m = N^2/\tau`: the Allan deviation falls as
    :math:`N/\sqrt\tau` (IEEE Std 952-1997, App. C). The differences are correlated
    (neighbours share a mean), so :math:`\sigma_A^2` is not exactly chi-square; ``edf`` is
    the two-moment (Satterthwaite) equivalent,
    :math:`\nu = (\operatorname{tr} A)^2/\operatorname{tr} A^2 = 2(K-1)^2/(3K-4)` for the
    quadratic form :math:`A = D^\top D`, so that :math:`\nu\,\sigma_A^2/E[\sigma_A^2]` is
    approximately :math:`\chi^2_\nu`.

    Parameters
    ----------
    y : (N,) finite samples. dt : sample interval (s), > 0. m : int or (M,) ints, cluster
    sizes with ``1 <= m <= N // 2`` (at least two clusters).

    Returns
    -------
    AllanDeviation with arrays of shape ``(M,)``.
    """
    y = as_vector(y, "y")
    if y.ndim != 1 or y.size < 2:
        raise ValueError(f"y must have shape (N,) with N >= 2, got shape {y.shape}")
    check_finite(y, "y")
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive sample interval (s), got {dt!r}")
    ms = np.atleast_1d(np.asarray(m))
    if ms.ndim != 1 or not np.issubdtype(ms.dtype, np.integer) or np.any(ms < 1) or np.any(ms > y.size // 2):
        raise ValueError(f"m must be integer cluster sizes in [1, {y.size // 2}] (N // 2 for N = {y.size}), got {m!r}")
    adev, Ks = np.empty(ms.size), np.empty(ms.size, dtype=int)
    for i, mi in enumerate(ms):
        K = y.size // mi
        means = y[: K * mi].reshape(K, mi).mean(axis=1)
        adev[i] = np.sqrt(np.sum(np.diff(means) ** 2) / (2 * (K - 1)))
        Ks[i] = K
    edf = 2.0 * (Ks - 1) ** 2 / (3.0 * Ks - 4.0)
    return AllanDeviation(ms * float(dt), adev, Ks, edf)

r"""Particle filters: the bootstrap (SIR) filter, an optimal-proposal filter for a linear-Gaussian
measurement, and a jump-Markov (multiple-model) particle filter, all in log weights and
broadcast over independent clouds (Monte Carlo runs).

Model, as everywhere in the book (:mod:`kftrack.ekf`):

.. math::

    x_{k+1} = f(x_k) + w_k,\quad w_k \sim N(0, Q), \qquad z_k = h(x_k) + v_k,\quad v_k \sim N(0, R).

The posterior :math:`p(x_k \mid z_{0:k})` is represented by ``N`` particles :math:`x^i_k` with
normalized weights :math:`w^i_k` (Gordon, Salmond & Smith 1993; Arulampalam et al. 2002). One
cycle of the **bootstrap filter** (:func:`bootstrap_filter`):

1. weight by the likelihood, in logs: :math:`\log w^i_k = \log w^i_{k-1} + \log N(z_k \ominus h(x^i_k); 0, R) - c`,
   normalized by log-sum-exp (a likelihood of :math:`e^{-10^6}` is handled exactly, where a
   linear weight underflows to zero for every particle);
2. estimate :math:`\hat x_k = \sum_i w^i x^i`, :math:`P_k = \sum_i w^i (x^i - \hat x)(x^i - \hat x)^\top`;
3. resample (:mod:`kftrack.resampling`) when the effective sample size
   :math:`N_\text{eff} = 1/\sum_i (w^i)^2` falls below ``threshold * N``; optionally
   **regularize** (Musso, Oudjane & Le Gland 2001): jitter the copies with the Gaussian kernel
   :math:`N(0, h^2 P_k)`, :math:`h = (4 / (N(n + 2)))^{1/(n + 4)}`, against sample impoverishment;
4. propagate, :math:`x^i_{k+1} = f(x^i_k) + w^i`, :math:`w^i \sim N(0, Q)`.

The **optimal proposal** (Doucet, Godsill & Andrieu 2000) for a linear measurement
:math:`z = Hx + v` draws :math:`x_k` from :math:`p(x_k \mid x_{k-1}, z_k)`, Gaussian with
:math:`S = HQH^\top + R`, :math:`K = QH^\top S^{-1}`, mean :math:`m + K(z - Hm)`,
covariance :math:`Q - KHQ` (:math:`m = f(x_{k-1})`), and weights by
:math:`p(z_k \mid x_{k-1}) = N(z_k; Hm, S)`, which does not depend on the new draw: the filter
can resample *before* it propagates (fully adapted, :func:`optimal_proposal_filter`).

The **jump-Markov particle filter** (:func:`jump_markov_filter`) gives every particle a mode
:math:`M \in \{0..r-1\}` that switches with the IMM's Markov matrix
``Pi[i, j] = P(mode j at k | mode i at k-1)`` (:mod:`kftrack.imm`) and moves it with that mode's
model of :mod:`kftrack.models` (``f(x, dt)``, ``Q(dt)``); the mode probabilities are the sums of
the weights per mode.

Shapes: particles ``(..., N, n)``, log weights ``(..., N)``; leading axes ``...`` are independent
filters, so one call runs every Monte Carlo run. Sequences are time first, ``(T, ..., m)``, and
``x0, P0`` is the prior of step 0 as in :func:`kftrack.kalman.kalman_filter`. Every function
that draws takes ``rng``, a ``numpy.random.Generator``. The user's functions (``f``, ``h``, a
model's ``f``) are checked right after every call: NaN or inf in their output raises
``ValueError`` naming the function and the step.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from . import resampling as rs
from ._validate import (as_float_array, as_matrix, as_measurement_sequence, as_vector, check_angles,
                        check_covariance, check_rng)
from .ekf import wrap_angle
from .imm import check_transition

__all__ = ["ParticleResult", "gaussian_particles", "cloud_moments", "kernel_bandwidth", "gaussian_log_likelihood",
           "propagate", "reweight", "resample", "regularize", "bootstrap_filter", "optimal_proposal_filter",
           "jump_markov_filter"]

Vector = Callable[[np.ndarray], np.ndarray]


class ParticleResult(NamedTuple):
    """A particle-filtered sequence, time first (``T`` steps).

    Attributes
    ----------
    x : (T, ..., n) posterior means :math:`\\sum_i w^i x^i` after each measurement.
    P : (T, ..., n, n) posterior covariances of the weighted cloud.
    ess : (T, ...) effective sample size after the update (before any resampling).
    resampled : (T, ...) whether the cloud was resampled at that step.
    log_evidence : (T, ...) :math:`\\log p(z_k \\mid z_{0:k-1})` (0 at steps without a measurement);
        its sum over time is the log-likelihood of the data.
    particles : (..., N, n) the cloud after the last update (before resampling).
    log_weights : (..., N) its normalized log weights.
    mu : (T, ..., r) mode probabilities (jump-Markov filter), else ``None``.
    modes : (..., N) the particles' modes at the last step (jump-Markov filter), else ``None``.
    """

    x: np.ndarray
    P: np.ndarray
    ess: np.ndarray
    resampled: np.ndarray
    log_evidence: np.ndarray
    particles: np.ndarray
    log_weights: np.ndarray
    mu: np.ndarray | None = None
    modes: np.ndarray | None = None


# --------------------------------------------------------------------------------------------
# checks
# --------------------------------------------------------------------------------------------
def _count(N, name: str = "N") -> int:
    if isinstance(N, bool) or not isinstance(N, (int, np.integer)) or N < 1:
        raise ValueError(f"{name} must be a positive integer number of particles, got {N!r}")
    return int(N)


def _threshold(threshold) -> float:
    t = as_float_array(threshold, "threshold")
    if t.ndim != 0 or not np.isfinite(t) or not 0.0 < float(t) <= 1.0:
        raise ValueError(f"threshold must be a number in (0, 1] (resample when N_eff < threshold * N), "
                         f"got {threshold!r}")
    return float(t)


def _method(method) -> str:
    if method not in rs.METHODS:
        raise ValueError(f"method must be one of {rs.METHODS}, got {method!r}")
    return method


def _angles(angle_components, m: int) -> tuple[int, ...]:
    return check_angles(angle_components, m)


def _user(fn, name: str, k: int | None, *args) -> np.ndarray:
    """``fn(*args)``, a user's function (``f``, ``h``, a model's ``f``), checked at the boundary
    between the user's code and the filter: a NaN or inf in its output raises ``ValueError``
    naming the function and the step ``k`` (instead of a misleading failure steps later)."""
    out = fn(*args)
    ok = np.isfinite(out)
    if not np.all(ok):
        bad = ~ok.all(axis=-1) if ok.ndim else ~ok
        what = "NaN" if np.isnan(out).any() else "inf"
        at = "" if k is None else f" at step {k}"
        raise ValueError(f"{name} returned {what}{at} for {int(np.sum(bad))} of {bad.size} particles; it must "
                         f"return finite values for every state it is given (e.g. no sqrt or log of a "
                         f"negative number)")
    return out


def _per_step(fn, name: str, count: int) -> list:
    """A callable, or a sequence of at least ``count`` callables (one per step)."""
    if callable(fn):
        return [fn] * count
    try:
        fns = list(fn)
    except TypeError:
        raise TypeError(f"{name} must be a callable or a sequence of callables, got {type(fn).__name__}") from None
    if len(fns) < count or not all(callable(g) for g in fns):
        raise ValueError(f"{name} must be a callable or a sequence of at least {count} callables (one per step), "
                         f"got {len(fns)} items")
    return fns


def _sqrt_psd(C: np.ndarray) -> np.ndarray:
    """The lower Cholesky factor ``L`` (``L L^T = C``) of a PSD, possibly singular, ``C`` (..., n, n).

    Computed column by column with elementwise NumPy operations: unlike an eigen-decomposition
    (whose eigenvectors are arbitrary within a repeated eigenvalue, as in the block-diagonal
    ``Q`` of every per-axis model) the factor is unique, so the particles, and every resampling
    decision made on them, do not depend on the BLAS/LAPACK kernels of the machine. A pivot
    below ``n * eps`` times the largest diagonal entry (a singular direction) gives a zero column.
    """
    C = np.asarray(C, dtype=float)
    n = C.shape[-1]
    L = np.zeros(C.shape)
    tol = n * np.finfo(float).eps * np.max(np.abs(np.diagonal(C, axis1=-2, axis2=-1)), axis=-1)
    for j in range(n):
        d = C[..., j, j] - np.sum(L[..., j, :j] ** 2, axis=-1)
        ok = d > tol
        ljj = np.sqrt(np.where(ok, d, 1.0))
        L[..., j, j] = np.where(ok, ljj, 0.0)
        for i in range(j + 1, n):
            v = (C[..., i, j] - np.sum(L[..., i, :j] * L[..., j, :j], axis=-1)) / ljj
            L[..., i, j] = np.where(ok, v, 0.0)
    return L


def _draw(rng, L: np.ndarray, shape: tuple) -> np.ndarray:
    """Gaussian noise ``(*batch, N, n)`` with covariance ``L L^T``; ``shape = (*batch, N)`` and ``L``
    ``(n, n)`` or ``(*batch, n, n)`` (one matrix product per cloud)."""
    eps = rng.standard_normal(tuple(shape) + (L.shape[-1],))
    return eps @ np.swapaxes(L, -1, -2)


# --------------------------------------------------------------------------------------------
# building blocks
# --------------------------------------------------------------------------------------------
def gaussian_particles(x0, P0, N: int, rng: np.random.Generator, batch: tuple = ()) -> np.ndarray:
    r"""``N`` draws from :math:`N(x_0, P_0)` for each cloud: ``(*batch, ..., N, n)``.

    ``x0`` ``(..., n)``, ``P0`` ``(..., n, n)`` (positive semi-definite; sampled through its
    eigen-decomposition, so a singular ``P0`` is fine); ``batch`` extra leading axes.
    """
    N = _count(N)
    check_rng(rng)
    x0 = as_vector(x0, "x0")
    n = x0.shape[-1]
    P0 = check_covariance(P0, "P0", n)
    shape = np.broadcast_shapes(tuple(batch) + x0.shape[:-1], P0.shape[:-2]) if batch else \
        np.broadcast_shapes(x0.shape[:-1], P0.shape[:-2])
    return x0[..., None, :] + _draw(rng, _sqrt_psd(P0), tuple(shape) + (N,))


def cloud_moments(particles, log_weights) -> tuple[np.ndarray, np.ndarray]:
    r"""Weighted mean :math:`\sum_i w^i x^i` ``(..., n)`` and covariance
    :math:`\sum_i w^i (x^i - \hat x)(x^i - \hat x)^\top` ``(..., n, n)`` of a cloud
    ``particles`` ``(..., N, n)`` with log weights ``(..., N)`` (normalized here)."""
    X = as_vector(particles, "particles")
    if X.ndim < 2:
        raise ValueError(f"particles must have shape (..., N, n), got shape {X.shape}")
    lw = rs.normalize_log_weights(log_weights)
    if lw.shape[-1] != X.shape[-2]:
        raise ValueError(f"log_weights must have shape (..., {X.shape[-2]}) (one per particle), got shape {lw.shape}")
    return _moments(X, np.exp(lw))


def _moments(X: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mean = (w[..., None, :] @ X)[..., 0, :]
    d = X - mean[..., None, :]
    P = np.swapaxes(d * w[..., None], -1, -2) @ d
    return mean, 0.5 * (P + np.swapaxes(P, -1, -2))


def kernel_bandwidth(N: int, n: int) -> float:
    r"""Optimal bandwidth of a Gaussian kernel for a Gaussian density (Musso et al. 2001):
    :math:`h = \left(\frac{4}{N(n + 2)}\right)^{1/(n + 4)}` (in units of the cloud's standard deviation)."""
    N, n = _count(N), _count(n, "n")
    return float((4.0 / (N * (n + 2.0))) ** (1.0 / (n + 4.0)))


def gaussian_log_likelihood(z, zhat, R, angle_components: Sequence[int] = ()) -> np.ndarray:
    r"""Log of :math:`N(z \ominus \hat z; 0, R)` for predicted measurements ``zhat`` ``(..., m)``
    (e.g. ``h(particles)`` ``(..., N, m)``) and a measurement ``z`` broadcastable against them;
    the ``angle_components`` of the residual are wrapped to :math:`(-\pi, \pi]`. Returns ``(...)``."""
    zhat = as_vector(zhat, "zhat")
    m = zhat.shape[-1]
    z = as_vector(z, "z", m)
    R = check_covariance(R, "R", m, positive_definite=True)
    return _loglik(z, zhat, _chol_inv(R), _angles(angle_components, m))


def _chol_inv(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(W, c)``: ``W`` with ``W^T W = R^{-1}`` and the constant ``-0.5 log det(2 pi R)``."""
    L = np.linalg.cholesky(R)
    W = np.linalg.inv(L)
    c = -np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1) - 0.5 * R.shape[-1] * np.log(2.0 * np.pi)
    return W, c


def _loglik(z, zhat, Wc, angles) -> np.ndarray:
    W, c = Wc
    y = z - zhat
    if angles:
        y = y.copy()
        y[..., angles] = wrap_angle(y[..., angles])
    if W.ndim == 2:
        u = y @ W.T
    else:
        u = y @ np.swapaxes(W, -1, -2)
    return -0.5 * np.sum(u * u, axis=-1) + (c if np.ndim(c) == 0 else c[..., None])


def propagate(particles, f: Vector, Q, rng: np.random.Generator) -> np.ndarray:
    r"""Bootstrap proposal :math:`x^i \leftarrow f(x^i) + w^i`, :math:`w^i \sim N(0, Q)`, for a cloud
    ``(..., N, n)``; ``f`` broadcasts ``(..., n) -> (..., n)`` (e.g. ``lambda x: model.f(x, dt)``)."""
    check_rng(rng)
    X = as_vector(particles, "particles")
    Q = check_covariance(Q, "Q", X.shape[-1])
    return _user(f, "f", None, X) + _draw(rng, _sqrt_psd(Q), X.shape[:-1])


def reweight(log_weights, loglik) -> tuple[np.ndarray, np.ndarray]:
    r"""Bayes' rule in logs: normalized :math:`\log w^i + \ell^i - \log\sum_l w^l e^{\ell^l}` ``(..., N)`` and
    the log evidence :math:`\log\sum_i w^i e^{\ell^i}` ``(...)`` (``log_weights`` normalized first).

    ``loglik`` may be ``-inf`` for impossible particles; NaN or ``+inf`` raise ``ValueError``."""
    lw = rs.normalize_log_weights(log_weights)
    ll = as_float_array(loglik, "loglik")
    if np.isnan(ll).any() or np.isposinf(ll).any():
        raise ValueError("loglik must be finite or -inf, but it contains NaN or +inf")
    new, ev = rs._normalize(lw + ll)
    if np.any(np.isneginf(ev)):
        raise ValueError("loglik gives every particle of a cloud zero likelihood (-inf everywhere)")
    return new, ev


def resample(particles, log_weights, rng: np.random.Generator, method: str = "systematic") -> np.ndarray:
    """Resample each cloud ``(..., N, n)`` by its log weights ``(..., N)``; returns the equally
    weighted copies ``(..., N, n)`` (their log weights are ``-log N``)."""
    X = as_vector(particles, "particles")
    lw = rs.normalize_log_weights(log_weights)
    idx = rs.resample_indices(np.exp(lw), rng, _method(method))
    return np.take_along_axis(X, idx[..., None], axis=-2)


def regularize(particles, P, rng: np.random.Generator, bandwidth: float | None = None, mean=None) -> np.ndarray:
    r"""Kernel jitter of an equally weighted cloud ``(..., N, n)``: add :math:`N(0, h^2 P)` to every
    particle, ``P`` ``(..., n, n)`` the cloud's covariance before resampling and ``h`` the
    bandwidth (default :func:`kernel_bandwidth`): the regularized particle filter of Musso et al. (2001).

    With ``mean`` ``(..., n)`` (the cloud's mean) the particles are first shrunk towards it,
    :math:`x \leftarrow a x + (1 - a)\bar x` with :math:`a = \sqrt{1 - h^2}` (Liu & West 2001), so
    the jittered cloud keeps the mean and covariance of the original in expectation instead of
    inflating the covariance by :math:`1 + h^2` at every resampling (``h < 1`` required)."""
    check_rng(rng)
    X = as_vector(particles, "particles")
    N, n = X.shape[-2], X.shape[-1]
    P = check_covariance(P, "P", n)
    h = kernel_bandwidth(N, n) if bandwidth is None else float(bandwidth)
    if not (np.isfinite(h) and h >= 0):
        raise ValueError(f"bandwidth must be a finite number >= 0, got {bandwidth!r}")
    if mean is not None:
        if h >= 1:
            raise ValueError(f"bandwidth must be < 1 with shrinkage (a = sqrt(1 - h^2)), got {h!r}")
        mean = as_vector(mean, "mean", n)
        a = np.sqrt(1.0 - h * h)
        X = a * X + (1.0 - a) * mean[..., None, :]
    return X + h * _draw(rng, _sqrt_psd(P), X.shape[:-1])


# --------------------------------------------------------------------------------------------
# whole sequences
# --------------------------------------------------------------------------------------------
def _common(zs, x0, P0, R, N, rng, method, threshold, angle_components=()):
    check_rng(rng)
    N = _count(N)
    method = _method(method)
    threshold = _threshold(threshold)
    zs, missing = as_measurement_sequence(zs, "zs")
    m = zs.shape[-1]
    x0 = as_vector(x0, "x0")
    n = x0.shape[-1]
    P0 = check_covariance(P0, "P0", n)
    R = check_covariance(R, "R", m, positive_definite=True)
    try:
        batch = np.broadcast_shapes(zs.shape[1:-1], x0.shape[:-1], P0.shape[:-2], R.shape[:-2])
    except ValueError:
        raise ValueError(f"the batch axes of zs[k] {zs.shape[1:-1]}, x0 {x0.shape[:-1]}, P0 {P0.shape[:-2]} and "
                         f"R {R.shape[:-2]} must broadcast") from None
    return zs, missing, x0, P0, R, N, n, m, tuple(batch), method, threshold, _angles(angle_components, m)


def _call_checked(fn, X, name: str, shape: tuple) -> np.ndarray:
    try:
        out = np.asarray(fn(X), dtype=float)
    except Exception as exc:
        raise ValueError(f"{name} failed on particles of shape {X.shape}: {exc}") from exc
    if out.shape[-len(shape):] != shape or out.shape[:-1] != X.shape[:-1]:
        raise ValueError(f"{name}(x) must map shape (..., n) to (..., {', '.join(map(str, shape))}), got {out.shape} "
                         f"for particles of shape {X.shape}")
    return out


def _weigh_and_record(out, k, lw, X, z, gone, h, Wc, angles):
    """Step ``k`` of a particle filter's loop: reweight by ``z`` (runs where ``gone`` keep their
    weights), then record the evidence, the weighted moments and the ESS :math:`1/\\sum w^2` in
    ``out``. Returns the log-weights and the weights."""
    if not gone.all():
        lw, ev = _reweight(lw, X, z, gone, h, Wc, angles, k)
        out.log_evidence[k] = np.where(gone, 0.0, ev)
    w = np.exp(lw)
    out.x[k], out.P[k] = _moments(X, w)
    out.ess[k] = 1.0 / np.sum(w * w, axis=-1)
    return lw, w


class _Recorder:
    def __init__(self, T, batch, n, r=None):
        self.x = np.empty((T,) + batch + (n,))
        self.P = np.empty((T,) + batch + (n, n))
        self.ess = np.empty((T,) + batch)
        self.resampled = np.zeros((T,) + batch, dtype=bool)
        self.log_evidence = np.zeros((T,) + batch)
        self.mu = None if r is None else np.empty((T,) + batch + (r,))


def _maybe_resample(X, lw, ess, N, threshold, rng, method, extra=None):
    """Resample the clouds whose ESS is below ``threshold * N``; returns ``(X, lw, extra, mask)``."""
    mask = ess < threshold * N
    if not mask.any():
        return X, lw, extra, mask
    if mask.all():  # the common case: every cloud, no masking copies
        idx = rs.resample_indices(np.exp(lw), rng, method)
        X = np.take_along_axis(X, idx[..., None], axis=-2)
        extra = None if extra is None else np.take_along_axis(extra, idx, axis=-1)
        return X, np.full(lw.shape, -np.log(N)), extra, mask
    idx = rs.resample_indices(np.exp(lw[mask]), rng, method)
    Xm = X.copy()
    Xm[mask] = np.take_along_axis(X[mask], idx[..., None], axis=-2)
    lw = lw.copy()
    lw[mask] = -np.log(N)
    if extra is not None:
        extra = extra.copy()
        extra[mask] = np.take_along_axis(extra[mask], idx, axis=-1)
    return Xm, lw, extra, mask


def _reweight(lw, X, z, gone, h, Wc, angles, k):
    """Bayes' rule on the log weights ``lw`` (..., N) of particles ``X`` (..., N, n) for the
    measurement ``z`` (..., m); runs with ``gone`` (no measurement) keep their weights.
    Returns the normalised log weights and the log evidence (..., )."""
    ll = _loglik(np.where(gone[..., None], 0.0, z)[..., None, :], _user(h, "h", k, X), Wc, angles)
    lw_new, ev = rs._normalize(lw + np.where(gone[..., None], 0.0, ll))
    if np.any(np.isneginf(ev) | np.isnan(ev)):
        raise ValueError(f"every particle of a cloud has zero likelihood at step {k} (the measurement is "
                         "impossible under the cloud); use more particles or a wider prior")
    return lw_new, ev


def bootstrap_filter(zs, x0, P0, f, Q, h, R, N: int, rng: np.random.Generator, *,
                     angle_components: Sequence[int] = (), method: str = "systematic", threshold: float = 0.5,
                     regularized: bool = False, bandwidth: float | None = None,
                     initial_size: int | None = None) -> ParticleResult:
    r"""Bootstrap (sampling-importance-resampling) particle filter over a measurement sequence.

    At each step: weight by :math:`N(z_k \ominus h(x^i); 0, R)` (log weights), estimate, resample
    when :math:`N_\text{eff} <` ``threshold * N`` (then regularize if asked), propagate with ``f``
    and ``Q``. Same time convention as :func:`kftrack.kalman.kalman_filter`.

    Parameters
    ----------
    zs : (T, ..., m) measurements, time first; a row of NaN is a missing measurement.
    x0, P0 : (..., n), (..., n, n) Gaussian prior of step 0 (the initial cloud is drawn from it).
    f : callable ``(..., n) -> (..., n)`` broadcasting over particles (``lambda x: model.f(x, dt)``),
        or a sequence of ``T - 1`` such callables (``f[k]`` maps step ``k`` to ``k + 1``).
    Q : (n, n) or (..., n, n) process-noise covariance (may be singular).
    h : callable ``(..., n) -> (..., m)`` (``sensor.h``), or a sequence of ``T`` callables (a moving sensor).
    R : (m, m) or (..., m, m) measurement-noise covariance, positive definite.
    N : number of particles per cloud, ``>= 1``.
    rng : numpy.random.Generator.
    angle_components : measurement components that are angles (residuals wrapped).
    method : resampling scheme, one of ``kftrack.resampling.METHODS``.
    threshold : resample when ``N_eff < threshold * N``; in (0, 1] (1: at almost every step).
    regularized : jitter resampled clouds with the kernel :math:`N(0, h^2 P_k)` after shrinking them
        towards their mean by :math:`\sqrt{1 - h^2}` (:func:`regularize` with ``mean``; Liu & West 2001).
    bandwidth : kernel bandwidth ``h`` (default :func:`kernel_bandwidth`).
    initial_size : draw this many particles (``>= N``) from the prior at step 0 and resample them
        down to ``N`` after its update (default ``N``). A cheap cure for a first measurement much more
        informative than the prior, which would otherwise leave a handful of effective
        particles; it is still sampling-importance-resampling, with more samples at one step.

    Returns
    -------
    ParticleResult

    Raises
    ------
    ValueError
        Naming the function and the step, if ``f`` or ``h`` returns NaN or inf (checked after
        every call); if every particle of a cloud has zero likelihood.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.kalman import kalman_filter
    >>> from kftrack.models import ConstantVelocity
    >>> from kftrack.particle import bootstrap_filter
    >>> cv = ConstantVelocity(ndim=1, q=0.1)          # state [x, vx]; position measured
    >>> zs = np.array([[0.0], [1.1], [np.nan], [2.9], [4.2]])
    >>> pf = bootstrap_filter(zs, np.zeros(2), 10 * np.eye(2), lambda x: cv.f(x, 1.0), cv.Q(1.0),
    ...                       lambda x: x[..., :1], np.eye(1), N=2000, rng=np.random.default_rng(0))
    >>> pf.x.shape, pf.ess.shape
    ((5, 2), (5,))
    >>> # linear and Gaussian: the Kalman filter is exact; over 30 seeds the particle mean of x
    >>> # differs from it by 0.04 (standard deviation), so 0.2 is five of them
    >>> kf = kalman_filter(zs, np.zeros(2), 10 * np.eye(2), cv.F(1.0), cv.Q(1.0), cv.H, np.eye(1))
    >>> bool(np.all(np.abs(pf.x[-1] - kf.x[-1]) < 0.2))
    True
    """
    zs, missing, x0, P0, R, N, n, m, batch, method, threshold, angles = _common(
        zs, x0, P0, R, N, rng, method, threshold, angle_components)
    T = zs.shape[0]
    fs = _per_step(f, "f", T - 1) if T > 1 else []
    hs = _per_step(h, "h", T)
    Q = check_covariance(Q, "Q", n)
    LQ = _sqrt_psd(Q)
    Wc = _chol_inv(R)
    N0 = N if initial_size is None else _count(initial_size, "initial_size")
    if N0 < N:
        raise ValueError(f"initial_size must be at least N = {N} (the particles drawn at step 0, resampled down "
                         f"to N after its update), got {initial_size!r}")
    X = gaussian_particles(np.broadcast_to(x0, batch + (n,)), P0, N0, rng)
    lw = np.full(batch + (N0,), -np.log(N0))
    _call_checked(hs[0], X, "h", (m,))
    if fs:
        _call_checked(fs[0], X, "f", (n,))
    out = _Recorder(T, batch, n)
    missing = np.broadcast_to(missing, (T,) + batch)
    for k in range(T):
        lw, w = _weigh_and_record(out, k, lw, X, zs[k], missing[k], hs[k], Wc, angles)
        X_last, lw_last = X, lw
        if k == T - 1:
            break
        if k == 0 and N0 != N:  # down to N particles: resample every cloud
            idx = rs.counts_to_indices(rs.offspring_counts(w, rng, method, size=N))
            X, lw = np.take_along_axis(X, idx[..., None], axis=-2), np.full(batch + (N,), -np.log(N))
            mask = np.ones(batch, dtype=bool)
        else:
            X, lw, _, mask = _maybe_resample(X, lw, out.ess[k], N, threshold, rng, method)
        out.resampled[k] = mask
        if regularized and mask.any():
            Lk = _sqrt_psd(out.P[k][mask])
            h_bw = kernel_bandwidth(N, n) if bandwidth is None else float(bandwidth)
            a = np.sqrt(1.0 - h_bw * h_bw)  # Liu-West shrinkage: the cloud keeps its mean and covariance
            X[mask] = a * X[mask] + (1.0 - a) * out.x[k][mask][..., None, :] + h_bw * _draw(rng, Lk, X[mask].shape[:-1])
        X = _user(fs[k], "f", k, X) + _draw(rng, LQ, X.shape[:-1])
    return ParticleResult(out.x, out.P, out.ess, out.resampled, out.log_evidence, X_last, lw_last)


def optimal_proposal_filter(zs, x0, P0, f, Q, H, R, N: int, rng: np.random.Generator, *,
                            method: str = "systematic", threshold: float = 0.5) -> ParticleResult:
    r"""Particle filter with the optimal proposal :math:`p(x_k \mid x_{k-1}, z_k)` for a **linear**
    measurement :math:`z = Hx + v` and any transition ``f`` (Doucet, Godsill & Andrieu 2000).

    With :math:`m^i = f(x^i_{k-1})` (at step 0, :math:`m = x_0` and ``P0`` in place of ``Q``),
    :math:`S = HQH^\top + R`, :math:`K = QH^\top S^{-1}`: weight by :math:`N(z_k; Hm^i, S)`,
    resample if :math:`N_\text{eff} <` ``threshold * N`` (before propagating: fully adapted),
    then draw :math:`x^i_k \sim N(m^i + K(z_k - Hm^i),\, Q - KHQ)`. The weights do not depend on
    the new draws, so an informative measurement does not collapse the cloud as it does in the
    bootstrap filter. Arguments as in :func:`bootstrap_filter`, with ``H`` ``(m, n)``.
    """
    zs, missing, x0, P0, R, N, n, m, batch, method, threshold, _ = _common(zs, x0, P0, R, N, rng, method, threshold)
    T = zs.shape[0]
    fs = _per_step(f, "f", T - 1) if T > 1 else []
    Q = check_covariance(Q, "Q", n)
    H = as_matrix(H, "H", m, n, origin=f"m = {m} from zs, n = {n} from x0")
    if fs:
        _call_checked(fs[0], np.broadcast_to(x0, batch + (1, n)), "f", (n,))

    def gains(C):
        S = H @ C @ H.T + R
        K = np.swapaxes(np.linalg.solve(S, H @ C), -1, -2)  # C H^T S^-1 (C, S symmetric)
        Sig = C - K @ H @ C
        return K, _sqrt_psd(0.5 * (Sig + np.swapaxes(Sig, -1, -2))), _chol_inv(S), _sqrt_psd(C)

    g0, gQ = gains(P0), gains(Q)
    out = _Recorder(T, batch, n)
    missing = np.broadcast_to(missing, (T,) + batch)
    M = np.broadcast_to(x0[..., None, :], batch + (N, n))
    lw = np.full(batch + (N,), -np.log(N))
    for k in range(T):
        K, LS, Wc, LC = g0 if k == 0 else gQ
        gone = missing[k]
        if k > 0:
            M = _user(fs[k - 1], "f", k - 1, X)
        zhat = M @ H.T
        if not gone.all():
            zk = np.where(gone[..., None], 0.0, zs[k])[..., None, :]
            ll = np.where(gone[..., None], 0.0, _loglik(zk, zhat, Wc, ()))
            joint = lw + ll
            lw_new, ev = rs._normalize(joint)
            lw = lw_new
            out.log_evidence[k] = np.where(gone, 0.0, ev)
            w = np.exp(lw)
            ess = 1.0 / np.sum(w * w, axis=-1)
            both = np.concatenate([M, zhat], axis=-1)
            both, lw, _, mask = _maybe_resample(both, lw, ess, N, threshold, rng, method)
            out.resampled[k] = mask
            M, zhat = both[..., :n], both[..., n:]
            X = M + (zk - zhat) @ np.swapaxes(K, -1, -2) + _draw(rng, LS, M.shape[:-1])
            if gone.any():  # runs without a measurement: the prior draw
                X = np.where(gone[..., None, None], M + _draw(rng, LC, M.shape[:-1]), X)
        else:
            X = M + _draw(rng, LC, M.shape[:-1])
        w = np.exp(lw)
        out.x[k], out.P[k] = _moments(X, w)
        out.ess[k] = 1.0 / np.sum(w * w, axis=-1)
    return ParticleResult(out.x, out.P, out.ess, out.resampled, out.log_evidence, X, lw)


def jump_markov_filter(zs, x0, P0, models: Sequence, transition, mu0, h, R, N: int, rng: np.random.Generator,
                       dt, *, angle_components: Sequence[int] = (), method: str = "systematic",
                       threshold: float = 0.5) -> ParticleResult:
    r"""Jump-Markov (multiple-model) bootstrap particle filter with the IMM's Markov matrix.

    Each particle carries a state and a mode. The initial modes are drawn from ``mu0``; before
    each propagation every particle draws its next mode :math:`j` from row ``Pi[i, :]`` of its
    mode :math:`i` and moves with ``models[j].f(x, dt)`` plus :math:`N(0,` ``models[j].Q(dt)``:math:`)`.
    The mode probabilities ``mu[k, ..., j]`` are the summed weights of the particles in mode
    :math:`j` after the update with ``zs[k]``: the particle version of the IMM's
    :math:`P\{M_k = j \mid Z^k\}` (:func:`kftrack.imm.imm_filter`).

    Parameters
    ----------
    zs, x0, P0, h, R, N, rng, angle_components, method, threshold : as in :func:`bootstrap_filter`.
    models : r motion models of the same state dimension with ``f(x, dt)`` and ``Q(dt)``
        (:class:`kftrack.models.ConstantVelocity`, :class:`~kftrack.models.KnownTurn`, ...).
    transition : ``(r, r)`` Markov matrix ``Pi[i, j] = P(mode j at k | mode i at k-1)``, or a
        callable ``dt -> Pi`` (:class:`kftrack.imm.SojournTransition`).
    mu0 : (r,) initial mode probabilities.
    dt : sampling interval after each step (s), scalar or ``(T,)``.

    Returns
    -------
    ParticleResult
        with ``mu`` ``(T, ..., r)`` and the last ``modes`` ``(..., N)``.
    """
    zs, missing, x0, P0, R, N, n, m, batch, method, threshold, angles = _common(
        zs, x0, P0, R, N, rng, method, threshold, angle_components)
    models = tuple(models)
    r = len(models)
    if r < 1:
        raise ValueError("models must be a non-empty sequence of motion models")
    for i, mdl in enumerate(models):
        if not (hasattr(mdl, "f") and hasattr(mdl, "Q")):
            raise TypeError(f"models[{i}] must have f(x, dt) and Q(dt), got {type(mdl).__name__}")
    T = zs.shape[0]
    d = as_float_array(dt, "dt")
    dts = np.full(T, float(d)) if d.ndim == 0 else d
    if dts.shape != (T,) or not np.all(np.isfinite(dts)) or np.any(dts < 0):
        raise ValueError(f"dt must be a finite scalar or have shape ({T},) with dt >= 0, got {dt!r}")
    Pi_of = transition if (callable(transition) and not isinstance(transition, np.ndarray)) else None
    Pi_fixed = None if Pi_of else check_transition(transition, r)
    mu0 = as_vector(mu0, "mu0", r)
    if mu0.ndim != 1 or np.any(mu0 < 0) or abs(mu0.sum() - 1.0) > 1e-9:
        raise ValueError(f"mu0 must be {r} non-negative probabilities summing to 1, got {mu0!r}")
    hs = _per_step(h, "h", T)
    Wc = _chol_inv(R)
    X = gaussian_particles(np.broadcast_to(x0, batch + (n,)), P0, N, rng)
    _call_checked(hs[0], X, "h", (m,))
    modes = rng.choice(r, size=batch + (N,), p=mu0)
    lw = np.full(batch + (N,), -np.log(N))
    out = _Recorder(T, batch, n, r)
    missing = np.broadcast_to(missing, (T,) + batch)
    for k in range(T):
        lw, w = _weigh_and_record(out, k, lw, X, zs[k], missing[k], hs[k], Wc, angles)
        out.mu[k] = np.stack([np.sum(np.where(modes == j, w, 0.0), axis=-1) for j in range(r)], axis=-1)
        X_last, lw_last, modes_last = X, lw, modes
        if k == T - 1:
            break
        X, lw, modes, mask = _maybe_resample(X, lw, out.ess[k], N, threshold, rng, method, modes)
        out.resampled[k] = mask
        if Pi_of is not None and (k == 0 or dts[k] != dts[k - 1]):  # rebuild only when the interval changes
            Pi_fixed = check_transition(Pi_of(dts[k]), r)
        Pi = Pi_fixed
        # next mode: inverse CDF of row Pi[mode] with one uniform per particle
        cdf = np.cumsum(Pi, axis=1)
        cdf[:, -1] = 1.0
        u = rng.random(modes.shape)
        modes = np.sum(u[..., None] >= cdf[modes][..., :-1], axis=-1) if r > 1 else np.zeros_like(modes)
        newX = np.empty_like(X)
        if k == 0 or dts[k] != dts[k - 1]:
            Ls = [_sqrt_psd(np.asarray(mdl.Q(dts[k]), dtype=float)) for mdl in models]
        for j, mdl in enumerate(models):
            sel = modes == j
            if sel.any():
                Lj = Ls[j]
                xs = X[sel]
                newX[sel] = _user(mdl.f, f"models[{j}].f", k, xs, dts[k]) + _draw(rng, Lj, xs.shape[:-1])
        X = newX
    return ParticleResult(out.x, out.P, out.ess, out.resampled, out.log_evidence, X_last, lw_last, out.mu, modes_last)

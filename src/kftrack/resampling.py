r"""Resampling for particle filters: multinomial, stratified, systematic and residual schemes.

A weighted cloud :math:`\{x^i, w^i\}_{i=1}^N` (weights normalized, :math:`\sum_i w^i = 1`) is
replaced by :math:`N` equally weighted copies; particle :math:`i` gets :math:`c_i` **offspring**.
Every scheme here is **unbiased**, :math:`E[c_i] = N w^i` (Douc, Cappé & Moulines 2005; Hol,
Schön & Gustafsson 2006), and they differ in the variance of the counts:

* ``"multinomial"``: :math:`c \sim \mathrm{Multinomial}(N, w)`, :math:`\operatorname{Var} c_i = N w^i(1 - w^i)`;
* ``"stratified"``: one uniform in each stratum, :math:`u_j = (j + U_j)/N`;
* ``"systematic"``: one uniform for all, :math:`u_j = (j + U)/N`; :math:`c_i` is
  :math:`\lfloor N w^i\rfloor` or :math:`\lceil N w^i\rceil` (the smallest possible variance
  for a single count), at the cost of a dependence between the counts;
* ``"residual"``: :math:`\lfloor N w^i\rfloor` copies deterministically, the remaining
  :math:`R = N - \sum_i \lfloor N w^i\rfloor` by a multinomial draw on the residual weights
  :math:`(N w^i - \lfloor N w^i\rfloor)/R`.

For stratified and systematic resampling particle :math:`i` receives the points :math:`u_j` in
:math:`[C_{i-1}, C_i)`, :math:`C_i = \sum_{l \le i} w^l`; the counts are computed from the
cumulative weights in closed form (no search), exactly and batched.

Shapes: ``weights`` ``(..., N)``; leading axes are independent clouds (Monte Carlo runs), each
resampled with its own random numbers in one call. Every function takes ``rng``, a
``numpy.random.Generator``.

The effective sample size :math:`N_\text{eff} = 1/\sum_i (w^i)^2` (Kong, Liu & Wong 1994) is
computed from **log** weights (:func:`effective_sample_size`), which never underflow.
"""
from __future__ import annotations

import numpy as np

from ._validate import as_float_array, check_rng

__all__ = ["METHODS", "normalize_log_weights", "effective_sample_size", "offspring_counts", "counts_to_indices",
           "resample_indices", "check_weights", "offspring_chi_square"]

METHODS = ("multinomial", "stratified", "systematic", "residual")


def _logsumexp(a: np.ndarray, axis: int = -1, keepdims: bool = False) -> np.ndarray:
    m = np.max(a, axis=axis, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    out = np.log(np.sum(np.exp(a - m), axis=axis, keepdims=True)) + m
    return out if keepdims else np.squeeze(out, axis=axis)


def _normalize(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalized log weights and the log of their sum, ``(..., N)`` and ``(...)``.

    The maximum is subtracted first (exact for nearby values, Sterbenz), so log weights of
    size 1e6 keep their differences to the last bit of the differences, not of 1e6."""
    m = np.max(a, axis=-1, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    d = a - m
    with np.errstate(divide="ignore", invalid="ignore"):  # a cloud of zero weights: -inf, reported by callers
        s = np.log(np.sum(np.exp(d), axis=-1, keepdims=True))
        return d - s, (s + m)[..., 0]


def check_weights(weights, name: str = "weights") -> np.ndarray:
    """Non-negative, finite weights ``(..., N)`` with a positive sum per cloud, normalized to sum 1.

    Raises ``ValueError`` naming ``name`` for NaN/inf, negative entries, an empty last axis or a
    cloud whose weights are all zero.
    """
    w = as_float_array(weights, name)
    if w.ndim == 0 or w.shape[-1] < 1:
        raise ValueError(f"{name} must have shape (..., N) with N >= 1 particles, got shape {w.shape}")
    if not np.all(np.isfinite(w)):
        bad = "NaN" if np.isnan(w).any() else "inf"
        raise ValueError(f"{name} must be finite, but it contains {bad}")
    if np.any(w < 0):
        raise ValueError(f"{name} must be non-negative, got a minimum of {w.min():.3g}")
    s = w.sum(axis=-1, keepdims=True)
    if np.any(s <= 0):
        raise ValueError(f"{name} must have a positive sum in every cloud, but {int(np.sum(s <= 0))} cloud(s) sum to 0 "
                         "(use log weights to avoid underflow)")
    return w / s


def _check_log_weights(log_weights, name: str = "log_weights") -> np.ndarray:
    lw = as_float_array(log_weights, name)
    if lw.ndim == 0 or lw.shape[-1] < 1:
        raise ValueError(f"{name} must have shape (..., N) with N >= 1 particles, got shape {lw.shape}")
    if np.isnan(lw).any() or np.isposinf(lw).any():
        raise ValueError(f"{name} must be finite or -inf (zero weight), but it contains "
                         f"{'NaN' if np.isnan(lw).any() else '+inf'}")
    if np.any(np.all(np.isneginf(lw), axis=-1)):
        raise ValueError(f"{name} must give every cloud a positive total weight, but a cloud has all -inf")
    return lw


def normalize_log_weights(log_weights) -> np.ndarray:
    r"""Normalized log weights :math:`\log w^i - \log\sum_l w^l` by log-sum-exp, ``(..., N)``.

    ``-inf`` (zero weight) is allowed; NaN, ``+inf`` or a cloud with every weight ``-inf`` raise
    ``ValueError`` naming ``log_weights``.
    """
    return _normalize(_check_log_weights(log_weights))[0]


def effective_sample_size(log_weights) -> np.ndarray:
    r"""Effective sample size :math:`N_\text{eff} = 1/\sum_i (w^i)^2` of (unnormalized) log weights ``(..., N)``.

    Computed as :math:`\exp(-\operatorname{logsumexp}(2\log \bar w))` with normalized
    :math:`\log\bar w`; between 1 (one particle holds all the weight) and ``N`` (equal weights).
    Returns ``(...)``.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.resampling import effective_sample_size
    >>> print(np.round(effective_sample_size(np.log([0.1, 0.2, 0.3, 0.4])), 6))   # 1 / sum(w²)
    3.333333
    """
    lw = normalize_log_weights(log_weights)
    return np.exp(-_logsumexp(2.0 * lw, axis=-1))


def _cumulative(w: np.ndarray) -> np.ndarray:
    C = np.cumsum(w, axis=-1)
    C[..., -1] = 1.0  # the last boundary is 1 exactly, whatever the round-off of the sum
    return np.minimum(C, 1.0)


def _counts_below(C: np.ndarray, rng: np.random.Generator, method: str, N: int) -> np.ndarray:
    """Number of the N resampling points below each cumulative weight ``C`` (..., N)."""
    batch = C.shape[:-1]
    NC = N * C
    if method == "systematic":
        U = rng.random(batch + (1,))
        # points (j + U)/N < C  <=>  j < N C - U: ceil(N C - U) of them, clipped to [0, N]
        return np.clip(np.ceil(NC - U), 0, N).astype(np.int64)
    # stratified: floor(N C) whole strata below C, plus the point of the stratum C falls in
    U = rng.random(batch + (N,))
    k = np.minimum(np.floor(NC), N - 1).astype(np.int64)
    frac = NC - k
    extra = np.take_along_axis(U, k, axis=-1) < frac
    return np.clip(k + extra, 0, N).astype(np.int64)


def offspring_counts(weights, rng: np.random.Generator, method: str = "systematic",
                     size: int | None = None) -> np.ndarray:
    r"""Offspring counts :math:`c_i` ``(..., N)`` of one resampling of each cloud, :math:`\sum_i c_i = N`.

    Parameters
    ----------
    weights : (..., N) non-negative weights (normalized here); leading axes are independent clouds.
    rng : numpy.random.Generator.
    method : one of ``METHODS`` (see the module docstring).
    size : number of offspring (default ``N``, the usual choice).

    Returns
    -------
    (..., N) integer counts with :math:`E[c_i] = \text{size}\cdot w^i` for every scheme.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.resampling import offspring_counts
    >>> offspring_counts(np.array([0.5, 0.25, 0.25, 0.0]), np.random.default_rng(0), "systematic")   # N w when whole
    array([2, 1, 1, 0])
    """
    check_rng(rng)
    w = check_weights(weights)
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    N = w.shape[-1] if size is None else size
    if int(N) != N or N < 1:
        raise ValueError(f"size must be a positive integer (number of offspring), got {size!r}")
    N = int(N)
    if method == "multinomial":
        return rng.multinomial(N, w).astype(np.int64)
    if method == "residual":
        base = np.floor(N * w)
        rest = N - base.sum(axis=-1)
        res = np.maximum(N * w - base, 0.0)
        tot = res.sum(axis=-1, keepdims=True)
        p = np.where(tot > 0, res / np.where(tot > 0, tot, 1.0), 1.0 / w.shape[-1])
        extra = rng.multinomial(rest.astype(np.int64), p)
        return (base.astype(np.int64) + extra).astype(np.int64)
    below = _counts_below(_cumulative(w), rng, method, N)
    return np.diff(below, axis=-1, prepend=0)


def counts_to_indices(counts) -> np.ndarray:
    """Ancestor indices ``(..., M)`` from offspring counts ``(..., N)`` that sum to the same ``M``
    in every cloud: particle ``i`` appears ``counts[..., i]`` times, in increasing order."""
    c = np.asarray(counts)
    if c.ndim == 0 or not np.issubdtype(c.dtype, np.integer) or np.any(c < 0):
        raise ValueError(f"counts must be non-negative integers of shape (..., N), got {c.dtype} of shape {c.shape}")
    M = c.sum(axis=-1)
    if M.size and np.any(M != M.flat[0]):
        raise ValueError("counts must sum to the same number of offspring in every cloud")
    M = int(M.flat[0]) if M.size else 0
    batch, N = c.shape[:-1], c.shape[-1]
    flat = c.reshape(-1, N)
    ends = np.cumsum(flat, axis=-1)  # exact integers
    B = flat.shape[0]
    offsets = (np.arange(B) * M)[:, None]
    targets = (np.arange(M)[None, :] + offsets).ravel()
    idx = np.searchsorted((ends + offsets).ravel(), targets, side="right") - (np.arange(B) * N).repeat(M)
    return idx.reshape(batch + (M,))


def resample_indices(weights, rng: np.random.Generator, method: str = "systematic") -> np.ndarray:
    """Ancestor indices ``(..., N)`` of one resampling of each cloud (see :func:`offspring_counts`).

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.resampling import resample_indices
    >>> resample_indices(np.array([0.5, 0.25, 0.25, 0.0]), np.random.default_rng(0), "residual")
    array([0, 0, 1, 2])
    """
    return counts_to_indices(offspring_counts(weights, rng, method))


def offspring_chi_square(counts, weights) -> tuple[float, int, float]:
    r"""Chi-square (Wald) test that offspring counts are unbiased, :math:`E[c] = N w`.

    ``counts`` ``(M, N)`` from ``M`` independent resamplings of one cloud with ``weights``
    ``(N,)``. The mean count vector :math:`\bar c` is asymptotically Gaussian with covariance
    :math:`\Sigma/M`, :math:`\Sigma` the covariance of one draw (scheme-dependent and singular,
    since the counts sum to ``N``), estimated from the draws; under unbiasedness
    :math:`X^2 = M\,(\bar c - Nw)^\top \Sigma^+ (\bar c - Nw) \sim \chi^2_{\operatorname{rank}\Sigma}`.
    A deviation along a direction in which the counts never vary is infinitely significant
    (``X^2 = inf``). Returns ``(X^2, dof, p_value)``.
    """
    c = np.asarray(counts, dtype=float)
    w = check_weights(weights)
    if c.ndim != 2 or w.ndim != 1 or c.shape[1] != w.shape[0] or c.shape[0] < 2:
        raise ValueError(f"counts must have shape (M, N) with M >= 2 draws of the N = {w.shape[-1]} weights, "
                         f"got shape {c.shape}")
    N = c[0].sum()
    d = c.mean(axis=0) - N * w
    lam, V = np.linalg.eigh(np.cov(c, rowvar=False))
    keep = lam > 1e-9 * max(lam.max(), 1e-300)
    proj = V.T @ d
    scale = np.sqrt(N) * np.finfo(float).eps * 100  # round-off of a mean of counts of size N
    if np.any(np.abs(proj[~keep]) > scale):
        return float("inf"), int(keep.sum()), 0.0
    stat = float(c.shape[0] * np.sum(proj[keep] ** 2 / lam[keep]))
    from scipy import stats  # only here: the module itself needs no SciPy

    dof = int(keep.sum())
    return stat, dof, float(stats.chi2.sf(stat, dof)) if dof else 1.0

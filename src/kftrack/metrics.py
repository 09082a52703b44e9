r"""Accuracy and consistency metrics: RMSE, NEES, NIS, ANEES and chi-square bounds.

Conventions (Bar-Shalom, Li & Kirubarajan 2001, §5.4):

* NEES :math:`\epsilon = (x - \hat x)^\top P^{-1} (x - \hat x)`, chi-square with ``n`` degrees
  of freedom for a consistent filter;
* NIS :math:`\epsilon_y = y^\top S^{-1} y`, chi-square with ``m`` degrees of freedom;
* over ``N`` Monte Carlo runs the *average* NEES :math:`\bar\epsilon = \frac1N\sum\epsilon_i`
  satisfies :math:`N\bar\epsilon \sim \chi^2_{Nn}`; ANEES is :math:`\bar\epsilon / n`.
"""
from __future__ import annotations

import numpy as np
from scipy import stats

from ._validate import as_vector, check_covariance

__all__ = ["rmse", "nees", "nis", "anees", "chi2_bounds"]


def rmse(estimate, truth, axis=None, *, vector: bool = False) -> np.ndarray:
    r"""Root-mean-square error :math:`\sqrt{\operatorname{mean}(e^2)}` with ``e = estimate - truth``.

    Parameters
    ----------
    estimate, truth : arrays of the same (broadcastable) shape.
    axis : axes to average over (``None``: all).
    vector : if True the last axis holds the components of one vector error, which are
        summed before averaging: :math:`\sqrt{\operatorname{mean}\lVert e\rVert^2}`
        (e.g. a 2-D position RMSE). ``axis`` then refers to the remaining axes.
    """
    est = np.asarray(estimate, dtype=float)
    tru = np.asarray(truth, dtype=float)
    try:
        err = est - tru
    except ValueError:
        raise ValueError(f"estimate and truth must have matching shapes, got {est.shape} and {tru.shape}") from None
    sq = np.sum(err**2, axis=-1) if vector else err**2
    return np.sqrt(np.mean(sq, axis=axis))


def _mahalanobis2(e: np.ndarray, C: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", e, np.linalg.solve(C, e[..., None])[..., 0])


def nees(truth, estimate, P) -> np.ndarray:
    r"""Normalized estimation error squared :math:`(x-\hat x)^\top P^{-1}(x-\hat x)`.

    ``truth``, ``estimate``: ``(..., n)``; ``P``: ``(..., n, n)`` positive definite. Returns ``(...)``.
    """
    est = as_vector(estimate, "estimate")
    n = est.shape[-1]
    tru = as_vector(truth, "truth", n)
    P = check_covariance(P, "P", n, positive_definite=True)
    return _mahalanobis2(tru - est, P)


def nis(y, S) -> np.ndarray:
    r"""Normalized innovation squared :math:`y^\top S^{-1} y`; ``y`` ``(..., m)``, ``S`` ``(..., m, m)``."""
    y = as_vector(y, "y")
    S = check_covariance(S, "S", y.shape[-1], positive_definite=True)
    return _mahalanobis2(y, S)


def anees(nees_values, dim: int, axis: int = 0) -> np.ndarray:
    r"""Average NEES normalized by the state dimension, :math:`\frac{1}{N n}\sum_i \epsilon_i`.

    ``nees_values`` holds one NEES per run along ``axis`` (runs first by default); a consistent
    filter gives values near 1. Compare with ``chi2_bounds(dim, runs, normalize=True)``.
    """
    if int(dim) != dim or dim < 1:
        raise ValueError(f"dim must be a positive integer, got {dim!r}")
    return np.mean(np.asarray(nees_values, dtype=float), axis=axis) / dim


def chi2_bounds(dof: int, runs: int = 1, confidence: float = 0.95, *, normalize: bool = False) -> tuple[float, float]:
    r"""Two-sided acceptance interval for the average of ``runs`` chi-square(``dof``) values.

    The sum of ``runs`` independent :math:`\chi^2_{dof}` values is :math:`\chi^2_{runs\cdot dof}`,
    so the average lies in

    .. math:: \left[\chi^{2}_{N d}\big(\tfrac{1-c}{2}\big)/N,\; \chi^{2}_{N d}\big(\tfrac{1+c}{2}\big)/N\right]

    with probability ``confidence``. With ``normalize=True`` the bounds are divided by ``dof``
    (for ANEES). Returns ``(lower, upper)``.
    """
    if int(dof) != dof or dof < 1:
        raise ValueError(f"dof must be a positive integer, got {dof!r}")
    if int(runs) != runs or runs < 1:
        raise ValueError(f"runs must be a positive integer, got {runs!r}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence!r}")
    total = int(dof) * int(runs)
    lo = stats.chi2.ppf(0.5 * (1.0 - confidence), total) / runs
    hi = stats.chi2.ppf(0.5 * (1.0 + confidence), total) / runs
    if normalize:
        lo, hi = lo / dof, hi / dof
    return float(lo), float(hi)

r"""Accuracy and consistency metrics: RMSE, NEES, NIS, ANEES and chi-square bounds.

Conventions (Bar-Shalom, Li & Kirubarajan 2001, §5.4):

* NEES :math:`\epsilon = (x - \hat x)^\top P^{-1} (x - \hat x)`, chi-square with ``n`` degrees
  of freedom for a consistent filter;
* NIS :math:`\epsilon_y = y^\top S^{-1} y`, chi-square with ``m`` degrees of freedom;
* over ``N`` Monte Carlo runs the *average* NEES :math:`\bar\epsilon = \frac1N\sum\epsilon_i`
  satisfies :math:`N\bar\epsilon \sim \chi^2_{Nn}`; ANEES is :math:`\bar\epsilon / n`.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import stats

from ._validate import as_float_array, as_matrix, as_vector, broadcast_batch, check_covariance, check_finite

__all__ = ["rmse", "nees", "nis", "anees", "chi2_bounds", "Consistency", "consistency", "PCRLB", "pcrlb",
           "running_rms", "mean_running_rms"]


def rmse(truth, estimate, axis=None, *, vector: bool = False) -> np.ndarray:
    r"""Root-mean-square error :math:`\sqrt{\operatorname{mean}(e^2)}` with ``e = estimate - truth``.

    Every metric of this module takes ``(truth, estimate, ...)`` (as :func:`nees`).

    Parameters
    ----------
    truth, estimate : arrays of the same (broadcastable) shape.
    axis : axes to average over (``None``: all).
    vector : if True the last axis holds the components of one vector error, which are
        summed before averaging: :math:`\sqrt{\operatorname{mean}\lVert e\rVert^2}`
        (e.g. a 2-D position RMSE). ``axis`` then refers to the remaining axes.

    ``truth`` and ``estimate`` must be finite (a NaN raises ``ValueError``: drop the missing
    entries, or the lost runs, before calling) and hold at least one value.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.metrics import rmse
    >>> print(round(float(rmse([0.0, 0.0, 0.0], [1.0, -1.0, 2.0])), 6))   # sqrt((1 + 1 + 4) / 3)
    1.414214
    >>> print(round(float(rmse(np.zeros((4, 2)), np.ones((4, 2)), vector=True)), 6))   # 2-D position error
    1.414214
    """
    tru = check_finite(as_float_array(truth, "truth"), "truth")
    est = check_finite(as_float_array(estimate, "estimate"), "estimate")
    try:
        err = est - tru
    except ValueError:
        raise ValueError(f"truth and estimate must have matching shapes, got {tru.shape} and {est.shape}") from None
    if err.size == 0:
        raise ValueError(f"truth and estimate must hold at least one value, got shapes {tru.shape} and {est.shape}")
    if vector and err.ndim == 0:
        raise ValueError("with vector=True, truth and estimate must have shape (..., d), got scalars")
    sq = np.sum(err**2, axis=-1) if vector else err**2
    return np.sqrt(np.mean(sq, axis=_check_axis(axis, sq.ndim, "the error" + (" (vector=True: last axis summed)" if vector else ""))))


def _check_axis(axis, ndim: int, what: str):
    """``None``, an int or a tuple of ints, each in ``[-ndim, ndim)``; else ``ValueError`` naming ``axis``."""
    if axis is None:
        return None
    axes = axis if isinstance(axis, tuple) else (axis,)
    for a in axes:
        if isinstance(a, bool) or not isinstance(a, (int, np.integer)):
            raise TypeError(f"axis must be None, an int or a tuple of ints, got {axis!r}")
        if not -ndim <= a < ndim:
            raise ValueError(f"axis {a} is out of range for {what} of {ndim} dimension(s) "
                             f"(valid: {-ndim} to {ndim - 1}), got axis={axis!r}")
    return axis


def _mahalanobis2(e: np.ndarray, C: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", e, np.linalg.solve(C, e[..., None])[..., 0])


def nees(truth, estimate, P) -> np.ndarray:
    r"""Normalized estimation error squared :math:`(x-\hat x)^\top P^{-1}(x-\hat x)`.

    ``truth``, ``estimate``: ``(..., n)``; ``P``: ``(..., n, n)`` positive definite. Returns ``(...)``.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.metrics import nees
    >>> print(np.round(nees(truth=[1.0, 2.0], estimate=[0.0, 0.0], P=np.diag([1.0, 4.0])), 6))   # 1/1 + 4/4
    2.0
    """
    est = as_vector(estimate, "estimate")
    n = est.shape[-1]
    tru = as_vector(truth, "truth", n)
    P = check_covariance(P, "P", n, positive_definite=True)
    broadcast_batch({"truth": tru.shape[:-1], "estimate": est.shape[:-1], "P": P.shape[:-2]})
    return _mahalanobis2(tru - est, P)


def nis(y, S) -> np.ndarray:
    r"""Normalized innovation squared :math:`y^\top S^{-1} y`; ``y`` ``(..., m)``, ``S`` ``(..., m, m)``.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.metrics import nis
    >>> print(np.round(nis([3.0], [[9.0]]), 6))       # y² / S
    1.0
    """
    y = as_vector(y, "y")
    S = check_covariance(S, "S", y.shape[-1], positive_definite=True)
    broadcast_batch({"y": y.shape[:-1], "S": S.shape[:-2]})
    return _mahalanobis2(y, S)


def anees(nees_values, dim: int, axis: int = 0) -> np.ndarray:
    r"""Average NEES normalized by the state dimension, :math:`\frac{1}{N n}\sum_i \epsilon_i`.

    ``nees_values`` holds one NEES per run along ``axis`` (runs first by default); a consistent
    filter gives values near 1. Compare with ``chi2_bounds(dim, runs, normalize=True)``.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.metrics import anees, chi2_bounds
    >>> print(np.round(anees(np.array([1.8, 2.2, 2.0, 2.0]), dim=2), 6))   # NEES of 4 runs, n = 2
    1.0
    >>> lo, hi = chi2_bounds(2, runs=4, normalize=True)   # 95 % interval for that average
    >>> bool(lo < 1.0 < hi)
    True
    """
    if int(dim) != dim or dim < 1:
        raise ValueError(f"dim must be a positive integer, got {dim!r}")
    values = as_float_array(nees_values, "nees_values")
    axis = _check_axis(axis, values.ndim, f"nees_values of shape {values.shape}")
    if np.isinf(values).any() or (values < 0).any():
        raise ValueError("nees_values must be non-negative and finite (NEES values), "
                         f"got a minimum of {np.nanmin(values):.3g} and a maximum of {np.nanmax(values):.3g}")
    return np.mean(values, axis=axis) / dim


def chi2_bounds(dof: int, runs: int = 1, confidence: float = 0.95, *, normalize: bool = False) -> tuple[float, float]:
    r"""Two-sided acceptance interval for the average of ``runs`` chi-square(``dof``) values.

    The sum of ``runs`` independent :math:`\chi^2_{dof}` values is :math:`\chi^2_{runs\cdot dof}`,
    so the average lies in

    .. math:: \left[\chi^{2}_{N d}\big(\tfrac{1-c}{2}\big)/N,\; \chi^{2}_{N d}\big(\tfrac{1+c}{2}\big)/N\right]

    with probability ``confidence``. With ``normalize=True`` the bounds are divided by ``dof``
    (for ANEES). Returns ``(lower, upper)``.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.metrics import chi2_bounds
    >>> print(np.round(chi2_bounds(2, runs=100), 4))  # average of 100 chi-square(2) values, 95 %
    [1.6273 2.4106]
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


# --------------------------------------------------------------------------------------------
# Monte Carlo consistency tests and the posterior Cramér–Rao lower bound (nonlinear filtering)
# --------------------------------------------------------------------------------------------


class Consistency(NamedTuple):
    r"""Monte Carlo consistency test of a chi-square statistic (NEES or NIS).

    Attributes
    ----------
    mean : (T,) average over the runs at each step (NaN where no run has a value).
    bounds : ``(lower, upper)`` acceptance interval of ``mean`` at one step, from
        :func:`chi2_bounds` with ``runs`` runs.
    inside : fraction of the steps whose ``mean`` lies inside ``bounds``; about
        ``confidence`` for a consistent filter.
    time_average : the average over all steps and runs.
    time_bounds : ``(lower, upper)`` interval of ``time_average`` for ``runs * steps``
        independent values (exact for NIS, whose values are white in time for a consistent
        filter; optimistic, i.e. too narrow, for NEES, whose values are correlated in time).
    dof, runs, steps : degrees of freedom, runs ``N`` and steps ``T`` used.
    """

    mean: np.ndarray
    bounds: tuple[float, float]
    inside: float
    time_average: float
    time_bounds: tuple[float, float]
    dof: int
    runs: int
    steps: int


def consistency(values, dof: int, confidence: float = 0.95, *, runs: int | None = None) -> Consistency:
    r"""Time-averaged NEES/NIS test over Monte Carlo runs (Bar-Shalom, Li & Kirubarajan 2001, §5.4).

    Parameters
    ----------
    values : (T, N) NEES or NIS values, time first, one column per Monte Carlo run. A row of
        NaN (a step without a measurement) is skipped.
    dof : degrees of freedom of each value (``n`` for NEES, ``m`` for NIS).
    confidence : two-sided probability of the acceptance intervals.
    runs : optional number of Monte Carlo runs ``N``. The shape alone cannot tell ``(T, N)``
        from a transposed ``(N, T)`` (both are 2-D; the bounds would then be computed with
        ``T`` runs): pass ``runs`` and a ``values`` whose second axis is not ``N`` raises
        ``ValueError``.

    Returns
    -------
    Consistency
        per-step averages with their :math:`\chi^2_{N d}/N` bounds, and the time average with
        its :math:`\chi^2_{N T d}/(N T)` bounds.
    """
    v = np.asarray(values, dtype=float)
    if v.ndim != 2:
        raise ValueError(f"values must have shape (T, N): time first, one column per run; got shape {v.shape}")
    if runs is not None:
        if isinstance(runs, bool) or not isinstance(runs, (int, np.integer)) or runs < 1:
            raise ValueError(f"runs must be a positive integer (the number of Monte Carlo runs), got {runs!r}")
        if v.shape[1] != runs:
            hint = " (it looks transposed, (N, T): pass values.T)" if v.shape[0] == runs else ""
            raise ValueError(f"values must have shape (T, N) = (T, {runs}) with runs={runs} as its second axis, "
                             f"got shape {v.shape}{hint}")
    if np.isinf(v).any() or (v < 0).any():
        raise ValueError("values must be non-negative NEES/NIS values (NaN rows for missing steps)")
    nan = np.isnan(v)
    partial = nan.any(1) & ~nan.all(1)
    if partial.any():
        raise ValueError(f"values has a row at step {int(np.argmax(partial))} that is only partly NaN")
    kept = v[~nan.all(1)]
    if kept.size == 0:
        raise ValueError("values has no finite row")
    steps, runs = kept.shape
    bounds = chi2_bounds(dof, runs, confidence)
    mean = np.full(v.shape[0], np.nan)
    mean[~nan.all(1)] = kept.mean(axis=1)
    m = kept.mean(axis=1)
    inside = float(np.mean((m >= bounds[0]) & (m <= bounds[1])))
    return Consistency(mean, bounds, inside, float(kept.mean()), chi2_bounds(dof, runs * steps, confidence),
                       int(dof), runs, steps)


class PCRLB(NamedTuple):
    """Posterior Cramér–Rao lower bounds, time first: ``P_prior`` ``(T, ..., n, n)`` bounds the
    one-step prediction error covariance (before measurement ``k``), ``P`` the filtered one,
    and ``J = inv(P)`` is the Fisher information."""

    P_prior: np.ndarray
    P: np.ndarray
    J: np.ndarray


def _sequence(value, name: str, steps: int, rows: int, cols: int, lengths: tuple[int, ...]) -> np.ndarray:
    arr = as_matrix(value, name, rows, cols)
    if arr.ndim == 2:
        return arr[None]
    if arr.shape[0] not in lengths:
        raise ValueError(f"{name} must have shape ({rows}, {cols}) or time first ({' or '.join(map(str, lengths))}, "
                         f"..., {rows}, {cols}), got shape {arr.shape}")
    return arr


def pcrlb(P0, F, Q, H, R, steps: int | None = None, *, average_runs: bool = False) -> PCRLB:
    r"""Posterior Cramér–Rao lower bound for additive-Gaussian models (Tichavský, Muravchik & Nehorai 1998).

    The posterior (Bayesian, van Trees) bound holds for **any** estimator, biased or not:
    :math:`E[(\hat x_k - x_k)(\hat x_k - x_k)^\top] \ge J_k^{-1}`, the expectation over the
    states *and* the measurements. For :math:`x_{k+1} = f_k(x_k) + w_k`, :math:`w_k \sim N(0, Q)`
    and :math:`z_k = h(x_k) + v_k`, :math:`v_k \sim N(0, R)`, Tichavský et al.'s general
    information recursion is

    .. math::

        J_{k+1} = D^{22}_k - D^{21}_k \big(J_k + D^{11}_k\big)^{-1} D^{12}_k, \qquad
        D^{11}_k = E[\tilde F_k^\top Q^{-1} \tilde F_k], \quad
        D^{12}_k = -E[\tilde F_k^\top]\, Q^{-1} = (D^{21}_k)^\top, \quad
        D^{22}_k = Q^{-1} + E[\tilde H_{k+1}^\top R^{-1} \tilde H_{k+1}],

    with :math:`\tilde F_k`, :math:`\tilde H_k` the Jacobians of :math:`f_k`, :math:`h` at the
    *true* state. When :math:`\tilde F_k = F_k` does not depend on the state (linear dynamics)
    and :math:`Q` is invertible, the matrix inversion lemma turns it into the Riccati
    (information-form) recursion that this function evaluates (also defined for singular
    :math:`Q`):

    .. math::

        J_0 = P_0^{-1} + E[H_0^\top R^{-1} H_0], \qquad
        J_{k+1} = (Q + F_k J_k^{-1} F_k^\top)^{-1} + E[H_{k+1}^\top R^{-1} H_{k+1}] .

    For nonlinear dynamics with random truths, :math:`E[\tilde F^\top Q^{-1} \tilde F] \ne
    E[\tilde F]^\top Q^{-1} E[\tilde F]` and the Riccati form is not the bound; use the
    general recursion. The measurement term may be nonlinear in either case (its expectation
    over random truths: ``average_runs``). Only :math:`Q + F J^{-1} F^\top` is inverted, so a
    singular ``Q`` (e.g. the rank-1 discrete white-noise acceleration) is fine, where the
    general form with :math:`Q^{-1}` fails. For a linear-Gaussian model the bound is the Kalman
    filter's covariance. The time convention is :func:`kftrack.kalman.kalman_filter`'s: ``P0``
    is the prior of step 0, measured at step 0.

    Parameters
    ----------
    P0 : (n, n) or (..., n, n) prior covariance, positive definite.
    F : (n, n) constant, or time first ``(T-1 or T, ..., n, n)`` (``F[k]`` maps step ``k`` to ``k+1``).
    Q : (n, n) or (..., n, n) process noise (may be singular).
    H : (m, n) constant, or time first ``(T, ..., m, n)``: the measurement Jacobians at the truth.
    R : (m, m) or (..., m, m) measurement noise, positive definite.
    steps : number of steps ``T``; needed when neither ``F`` nor ``H`` is a sequence.
    average_runs : if True, ``H`` is ``(T, N, m, n)``, the Jacobians at ``N`` random truths,
        and :math:`E[H^\top R^{-1} H]` is their average (a Monte Carlo expectation).

    Returns
    -------
    PCRLB
        ``(P_prior, P, J)``, each ``(T, ..., n, n)``.
    """
    P0 = check_covariance(P0, "P0", positive_definite=True)
    n = P0.shape[-1]
    Q = check_covariance(Q, "Q", n)
    R = check_covariance(R, "R", positive_definite=True)
    m = R.shape[-1]
    Harr = np.asarray(H, dtype=float)
    Farr = np.asarray(F, dtype=float)
    if steps is None:
        if Harr.ndim > 2:
            steps = Harr.shape[0]
        elif Farr.ndim > 2:
            steps = Farr.shape[0] + 1
        else:
            raise ValueError("steps must be given when F and H are both constant matrices")
    if int(steps) != steps or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    T = int(steps)
    Fs = _sequence(F, "F", T, n, n, (T - 1, T))
    Hs = _sequence(H, "H", T, m, n, (T,))
    if average_runs and Hs.ndim != 4:
        raise ValueError(f"with average_runs=True, H must have shape (T, N, {m}, {n}), got shape {Harr.shape}")
    HtRinvH = np.swapaxes(Hs, -1, -2) @ np.linalg.solve(R, Hs)
    if average_runs:
        HtRinvH = HtRinvH.mean(axis=1)
    Bp = P0
    out_Bp, out_B, out_J = [], [], []
    for k in range(T):
        Jk = np.linalg.inv(Bp) + HtRinvH[min(k, len(HtRinvH) - 1)]
        Jk = 0.5 * (Jk + np.swapaxes(Jk, -1, -2))
        Bk = np.linalg.inv(Jk)
        Bk = 0.5 * (Bk + np.swapaxes(Bk, -1, -2))
        out_Bp.append(Bp)
        out_B.append(Bk)
        out_J.append(Jk)
        Fk = Fs[min(k, len(Fs) - 1)]
        Bp = Fk @ Bk @ np.swapaxes(Fk, -1, -2) + Q
        Bp = 0.5 * (Bp + np.swapaxes(Bp, -1, -2))
    shape = np.broadcast_shapes(*(a.shape for a in out_B))
    return PCRLB(*(np.stack([np.broadcast_to(a, shape) for a in lst]) for lst in (out_Bp, out_B, out_J)))


# --------------------------------------------------------------------------------------------
# Seed 001's running RMS (Agner Júnior et al. 2019, eqs. 44–46; chapter 12)
# --------------------------------------------------------------------------------------------


def running_rms(errors) -> np.ndarray:
    r"""Running RMS over time of each error component (seed 001, eq. 44):

    .. math:: \mathrm{RMS}^i_k = \sqrt{\frac1k\sum_{j=1}^{k}\big(e^i_j\big)^2}, \qquad k = 1, \dots, n .

    Parameters
    ----------
    errors : (n, ..., d) errors, time first (e.g. one-step prediction minus true position per
        axis). Restart the sum at a segment's start by passing only that segment.

    Returns
    -------
    (n, ..., d) running RMS.
    """
    e = check_finite(as_float_array(errors, "errors"), "errors")
    if e.ndim < 1 or e.shape[0] < 1:
        raise ValueError(f"errors must have shape (n, ..., d) with n >= 1 time steps, got shape {e.shape}")
    k = np.arange(1, e.shape[0] + 1).reshape((-1,) + (1,) * (e.ndim - 1))
    return np.sqrt(np.cumsum(e**2, axis=0) / k)


def mean_running_rms(errors) -> tuple[np.ndarray, np.ndarray]:
    r"""Seed 001's accuracy criterion: the mean over time of the running RMS per component
    (eq. 45) and its Euclidean norm over the components (eq. 46),

    .. math::

        \overline{\mathrm{RMS}}_i = \frac1n\sum_{k=1}^n \mathrm{RMS}^i_k, \qquad
        \lVert\overline{\mathrm{RMS}}\rVert = \sqrt{\textstyle\sum_i \overline{\mathrm{RMS}}_i^{\,2}} .

    It weighs early errors more than late ones (error :math:`j` enters every
    :math:`\mathrm{RMS}_k` with :math:`k \ge j`), so it is not the usual RMSE.

    Parameters
    ----------
    errors : (n, ..., d) errors, time first, components last (see :func:`running_rms`).

    Returns
    -------
    rms_bar : (..., d) eq. 45; norm : (...) eq. 46.
    """
    e = as_float_array(errors, "errors")
    if e.ndim < 2:
        raise ValueError(f"errors must have shape (n, ..., d) (time first, components last), got shape {e.shape}")
    rms_bar = np.mean(running_rms(e), axis=0)
    return rms_bar, np.sqrt(np.sum(rms_bar**2, axis=-1))

r"""The linear Kalman filter: predict, update, a whole-sequence filter and the RTS smoother.

Shapes broadcast over leading batch axes, so one call filters one track or many Monte
Carlo runs at once:

* state ``x``: ``(..., n)``; covariance ``P``: ``(..., n, n)``;
* measurement ``z``: ``(..., m)``;
* ``F``, ``Q`` ``(n, n)`` and ``H`` ``(m, n)``, ``R`` ``(m, m)``, either shared or with the
  same leading batch axes as ``x``.

Time series put time first: ``(T, ..., n)``.

The unchecked kernels behind these functions live in :mod:`kftrack.kernels`.

Equations (Bar-Shalom, Li & Kirubarajan 2001, §5.2):

.. math::

    x^- = F x, \quad P^- = F P F^\top + Q

    y = z - H x^-, \quad S = H P^- H^\top + R, \quad K = P^- H^\top S^{-1}

    x^+ = x^- + K y, \quad P^+ = (I - K H) P^- (I - K H)^\top + K R K^\top \;\text{(Joseph form)}
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ._validate import as_matrix, as_vector, broadcast_batch, check_covariance, check_form, check_sequence, check_state
from .kernels import Update, kf_predict, kf_update, matrix_transpose, mv, run_sequence, sym

__all__ = ["Update", "FilterResult", "SmootherResult", "predict", "update", "kalman_filter", "rts_smoother"]


class FilterResult(NamedTuple):
    """A filtered sequence, time first.

    ``x_prior[k]``, ``P_prior[k]`` are the predictions for step ``k`` before its measurement
    (``x_prior[0] = x0``); ``x[k]``, ``P[k]`` the estimates after it. ``nis`` and ``loglik`` are
    NaN at steps without a measurement.
    """

    x_prior: np.ndarray
    P_prior: np.ndarray
    x: np.ndarray
    P: np.ndarray
    nis: np.ndarray
    loglik: np.ndarray


class SmootherResult(NamedTuple):
    """Rauch–Tung–Striebel smoothed sequence: means ``x`` ``(T, ..., n)``, covariances ``P``
    ``(T, ..., n, n)`` and smoother gains ``G`` ``(T-1, ..., n, n)``."""

    x: np.ndarray
    P: np.ndarray
    G: np.ndarray


def predict(x, P, F, Q) -> tuple[np.ndarray, np.ndarray]:
    r"""Time update :math:`x^- = F x`, :math:`P^- = F P F^\top + Q`.

    Parameters
    ----------
    x : (..., n) state mean.
    P : (..., n, n) state covariance, symmetric positive semi-definite.
    F : (n, n) or (..., n, n) transition matrix.
    Q : (n, n) or (..., n, n) process-noise covariance of the step (a discrete covariance).

    Returns
    -------
    x, P : the predicted mean ``(..., n)`` and covariance ``(..., n, n)``.
    """
    x, P, n = check_state(x, P)
    F = as_matrix(F, "F", n, n, origin=f"n = {n} from x")
    Q = check_covariance(Q, "Q", n, origin=f"n = {n} from x")
    broadcast_batch({"x": x.shape[:-1], "P": P.shape[:-2], "F": F.shape[:-2], "Q": Q.shape[:-2]})
    return kf_predict(x, P, F, Q)


def update(x, P, z, H, R, *, form: str = "joseph") -> Update:
    r"""Measurement update, by default with the Joseph-form covariance.

    Parameters
    ----------
    x : (..., n) prior mean.
    P : (..., n, n) prior covariance.
    z : (..., m) measurement.
    H : (m, n) or (..., m, n) measurement matrix.
    R : (m, m) or (..., m, m) measurement-noise covariance, positive definite.
    form : ``"joseph"`` (default), :math:`P^+ = (I-KH)P^-(I-KH)^\top + KRK^\top`, symmetrized;
        or ``"standard"``, the short form :math:`P^+ = (I-KH)P^-` returned exactly as computed
        (not symmetrized), to study its round-off (Grewal & Andrews 2001).

    Returns
    -------
    Update
        ``(x, P, y, S, K, nis, loglik)``; see :class:`Update`.
    """
    form = check_form(form)
    x, P, n = check_state(x, P)
    z = as_vector(z, "z")
    m = z.shape[-1]
    H = as_matrix(H, "H", m, n, origin=f"m = {m} from z, n = {n} from x")
    R = check_covariance(R, "R", m, positive_definite=True, origin=f"m = {m} from z")
    broadcast_batch({"x": x.shape[:-1], "P": P.shape[:-2], "z": z.shape[:-1], "H": H.shape[:-2], "R": R.shape[:-2]})
    return kf_update(x, P, z, H, R, form)


def kalman_filter(zs, x0, P0, F, Q, H, R, *, progress: bool = False) -> FilterResult:
    """Filter a whole measurement sequence: at each step update with ``zs[k]``, then predict.

    A measurement row that is all NaN means "no measurement at this step": the filter only
    predicts across it. Validation happens once here; the loop runs unchecked kernels.

    Parameters
    ----------
    zs : (T, ..., m) measurements, time first; rows of NaN mark missing measurements.
    x0 : (..., n) prior mean for step 0 (before ``zs[0]``).
    P0 : (..., n, n) prior covariance for step 0.
    F, Q, H, R : as in :func:`predict` and :func:`update`, constant over time.
    progress : show a progress bar (tqdm) over the time steps.

    Returns
    -------
    FilterResult
        priors and posteriors ``(T, ..., n)``, ``(T, ..., n, n)``; ``nis``, ``loglik`` ``(T, ...)``.
    """
    zs, x0, P0, Q, R, n, m, batch, row_missing = check_sequence(zs, x0, P0, Q, R)
    F = as_matrix(F, "F", n, n, origin=f"n = {n} from x0")
    H = as_matrix(H, "H", m, n, origin=f"m = {m} from zs, n = {n} from x0")
    batch = broadcast_batch({"zs, x0, P0, Q, R": batch, "F": F.shape[:-2], "H": H.shape[:-2]})
    return run_sequence(zs, x0, P0, batch, row_missing,
                        lambda x, P: kf_predict(x, P, F, Q),
                        lambda x, P, z: kf_update(x, P, z, H, R), progress)


def rts_smoother(result: FilterResult, F) -> SmootherResult:
    r"""Rauch–Tung–Striebel smoother over a :class:`FilterResult` (Särkkä 2013, Thm 8.2).

    .. math::

        G_k = P_k F^\top (P^-_{k+1})^{-1}, \quad
        x^s_k = x_k + G_k (x^s_{k+1} - x^-_{k+1}), \quad
        P^s_k = P_k + G_k (P^s_{k+1} - P^-_{k+1}) G_k^\top

    Parameters
    ----------
    result : the output of :func:`kalman_filter` (the same ``F`` must be passed).
    F : (n, n) or (..., n, n) transition matrix used by the filter.
    """
    if not isinstance(result, FilterResult):
        raise TypeError(f"result must be a FilterResult from kalman_filter, got {type(result).__name__}")
    n = result.x.shape[-1]
    F = as_matrix(F, "F", n, n, origin=f"n = {n} from the filter's states")
    batch = result.x.shape[1:-1]
    if broadcast_batch({"result": batch, "F": F.shape[:-2]}) != batch:
        raise ValueError(f"F must have shape ({n}, {n}) or the filter's batch axes {batch} + ({n}, {n}), "
                         f"got shape {F.shape}")
    T = result.x.shape[0]
    xs, Ps = result.x.copy(), result.P.copy()
    G = np.empty((max(T - 1, 0),) + result.P.shape[1:])
    for k in range(T - 2, -1, -1):
        # G_k = P_k F^T (P^-_{k+1})^{-1}, solved as (P^-_{k+1})^T G_k^T = F P_k
        Gk = matrix_transpose(np.linalg.solve(result.P_prior[k + 1], F @ result.P[k]))
        xs[k] = result.x[k] + mv(Gk, xs[k + 1] - result.x_prior[k + 1])
        Ps[k] = sym(result.P[k] + Gk @ (Ps[k + 1] - result.P_prior[k + 1]) @ matrix_transpose(Gk))
        G[k] = Gk
    return SmootherResult(xs, Ps, G)

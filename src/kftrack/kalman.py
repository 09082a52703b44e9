r"""The linear Kalman filter: predict, update, a whole-sequence filter and the RTS smoother.

Shapes broadcast over leading batch axes, so one call filters one track or many Monte
Carlo runs at once:

* state ``x``: ``(..., n)``; covariance ``P``: ``(..., n, n)``;
* measurement ``z``: ``(..., m)``;
* ``F``, ``Q`` ``(n, n)`` and ``H`` ``(m, n)``, ``R`` ``(m, m)``, either shared or with the
  same leading batch axes as ``x``.

Time series put time first: ``(T, ..., n)``.

Equations (Bar-Shalom, Li & Kirubarajan 2001, §5.2):

.. math::

    x^- = F x, \quad P^- = F P F^\top + Q

    y = z - H x^-, \quad S = H P^- H^\top + R, \quad K = P^- H^\top S^{-1}

    x^+ = x^- + K y, \quad P^+ = (I - K H) P^- (I - K H)^\top + K R K^\top \;\text{(Joseph form)}
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ._validate import as_matrix, as_measurement_sequence, as_vector, check_covariance

__all__ = ["Update", "FilterResult", "SmootherResult", "predict", "update", "kalman_filter", "rts_smoother"]

_LOG_2PI = np.log(2.0 * np.pi)


class Update(NamedTuple):
    """Result of a measurement update; every field broadcasts over the batch axes.

    Attributes
    ----------
    x : (..., n) posterior mean.
    P : (..., n, n) posterior covariance (Joseph form, symmetric; with ``form="standard"`` the
        short form :math:`(I - KH)P`, not symmetrized).
    y : (..., m) innovation ``z - H x``.
    S : (..., m, m) innovation covariance ``H P H^T + R``.
    K : (..., n, m) Kalman gain.
    nis : (...) normalized innovation squared ``y^T S^{-1} y``.
    loglik : (...) Gaussian log-likelihood ``log N(y; 0, S)``.
    """

    x: np.ndarray
    P: np.ndarray
    y: np.ndarray
    S: np.ndarray
    K: np.ndarray
    nis: np.ndarray
    loglik: np.ndarray


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


def _mv(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    return (A @ v[..., None])[..., 0]


def _T(A: np.ndarray) -> np.ndarray:
    return np.swapaxes(A, -1, -2)


def _sym(A: np.ndarray) -> np.ndarray:
    return 0.5 * (A + _T(A))


def _batch(name_shapes: dict[str, tuple]) -> tuple:
    try:
        return np.broadcast_shapes(*name_shapes.values())
    except ValueError:
        desc = ", ".join(f"{k} {v}" for k, v in name_shapes.items())
        raise ValueError(f"batch axes do not broadcast: {desc}; the leading (batch) axes of the arguments "
                         "must be equal or 1 (NumPy broadcasting), or absent for a shared matrix") from None


def _predict(x, P, F, Q):
    return _mv(F, x), _sym(F @ P @ _T(F) + Q)


_FORMS = ("joseph", "standard")


def _check_form(form) -> str:
    if form not in _FORMS:
        raise ValueError(f"form must be one of {_FORMS} (covariance update), got {form!r}")
    return form


def _innovation_score(y, S) -> tuple[np.ndarray, np.ndarray]:
    r"""NIS :math:`y^\top S^{-1} y` and Gaussian log-likelihood :math:`\log N(y; 0, S)` of an innovation."""
    Sinv_y = np.linalg.solve(S, y[..., None])[..., 0]
    nis = np.einsum("...i,...i->...", y, Sinv_y)
    _, logdet = np.linalg.slogdet(S)
    return nis, -0.5 * (nis + logdet + y.shape[-1] * _LOG_2PI)


def _update(x, P, z, H, R, form: str = "joseph") -> Update:
    y = z - _mv(H, x)
    PHt = P @ _T(H)
    S = _sym(H @ PHt + R)
    K = _T(np.linalg.solve(S, _T(PHt)))  # S symmetric: K^T = S^{-1} H P
    x_post = x + _mv(K, y)
    I_KH = np.eye(x.shape[-1]) - K @ H
    if form == "joseph":
        P_post = _sym(I_KH @ P @ _T(I_KH) + K @ R @ _T(K))
    else:  # "standard": the short form (I - KH) P, as computed (not symmetrized)
        P_post = I_KH @ P
    return Update(x_post, P_post, y, S, K, *_innovation_score(y, S))


def _check_state(x, P, names: tuple[str, str] = ("x", "P")):
    x = as_vector(x, names[0])
    n = x.shape[-1]
    P = check_covariance(P, names[1], n, origin=f"n = {n} from {names[0]}")
    return x, P, n


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
    x, P, n = _check_state(x, P)
    F = as_matrix(F, "F", n, n, origin=f"n = {n} from x")
    Q = check_covariance(Q, "Q", n, origin=f"n = {n} from x")
    _batch({"x": x.shape[:-1], "P": P.shape[:-2], "F": F.shape[:-2], "Q": Q.shape[:-2]})
    return _predict(x, P, F, Q)


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
    form = _check_form(form)
    x, P, n = _check_state(x, P)
    z = as_vector(z, "z")
    m = z.shape[-1]
    H = as_matrix(H, "H", m, n, origin=f"m = {m} from z, n = {n} from x")
    R = check_covariance(R, "R", m, positive_definite=True, origin=f"m = {m} from z")
    _batch({"x": x.shape[:-1], "P": P.shape[:-2], "z": z.shape[:-1], "H": H.shape[:-2], "R": R.shape[:-2]})
    return _update(x, P, z, H, R, form)


def _check_sequence(zs, x0, P0, Q, R):
    """Boundary checks shared by the whole-sequence filters (KF, EKF, UKF).

    Returns ``zs, x0, P0, Q, R, n, m, batch, row_missing`` where ``row_missing`` ``(T, ...)``
    marks the all-NaN measurement rows.
    """
    x0, P0, n = _check_state(x0, P0, ("x0", "P0"))
    zs, row_missing = as_measurement_sequence(zs, "zs")
    m = zs.shape[-1]
    Q = check_covariance(Q, "Q", n, origin=f"n = {n} from x0")
    R = check_covariance(R, "R", m, positive_definite=True, origin=f"m = {m} from zs")
    batch = _batch({"zs[k]": zs.shape[1:-1], "x0": x0.shape[:-1], "P0": P0.shape[:-2],
                    "Q": Q.shape[:-2], "R": R.shape[:-2]})
    return zs, x0, P0, Q, R, n, m, batch, row_missing


def _run_sequence(zs, x0, P0, batch, row_missing, predict, update, progress: bool = False) -> FilterResult:
    """The time loop of every whole-sequence filter: at step ``k`` update with ``zs[k]`` (unless
    the row is missing), then predict. ``predict(x, P) -> (x, P)``, ``update(x, P, z) -> Update``
    are unchecked kernels; ``progress`` shows a tqdm bar."""
    T, n = zs.shape[0], x0.shape[-1]
    x = np.broadcast_to(x0, batch + (n,)).copy()
    P = np.broadcast_to(P0, batch + (n, n)).copy()
    out_xp = np.empty((T,) + batch + (n,))
    out_Pp = np.empty((T,) + batch + (n, n))
    out_x, out_P = np.empty_like(out_xp), np.empty_like(out_Pp)
    out_nis = np.full((T,) + batch, np.nan)
    out_ll = np.full((T,) + batch, np.nan)
    steps = range(T)
    if progress:
        from tqdm.auto import tqdm  # only when asked for

        steps = tqdm(steps, desc="filter", unit="step")
    for k in steps:
        out_xp[k], out_Pp[k] = x, P
        gone = np.broadcast_to(row_missing[k], batch)
        if not gone.all():
            z = np.where(gone[..., None], 0.0, zs[k])
            upd = update(x, P, z)
            x = np.where(gone[..., None], x, upd.x)
            P = np.where(gone[..., None, None], P, upd.P)
            out_nis[k] = np.where(gone, np.nan, upd.nis)
            out_ll[k] = np.where(gone, np.nan, upd.loglik)
        out_x[k], out_P[k] = x, P
        x, P = predict(x, P)
    return FilterResult(out_xp, out_Pp, out_x, out_P, out_nis, out_ll)


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
    zs, x0, P0, Q, R, n, m, batch, row_missing = _check_sequence(zs, x0, P0, Q, R)
    F = as_matrix(F, "F", n, n, origin=f"n = {n} from x0")
    H = as_matrix(H, "H", m, n, origin=f"m = {m} from zs, n = {n} from x0")
    batch = _batch({"zs, x0, P0, Q, R": batch, "F": F.shape[:-2], "H": H.shape[:-2]})
    return _run_sequence(zs, x0, P0, batch, row_missing,
                         lambda x, P: _predict(x, P, F, Q),
                         lambda x, P, z: _update(x, P, z, H, R), progress)


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
    if _batch({"result": batch, "F": F.shape[:-2]}) != batch:
        raise ValueError(f"F must have shape ({n}, {n}) or the filter's batch axes {batch} + ({n}, {n}), "
                         f"got shape {F.shape}")
    T = result.x.shape[0]
    xs, Ps = result.x.copy(), result.P.copy()
    G = np.empty((max(T - 1, 0),) + result.P.shape[1:])
    for k in range(T - 2, -1, -1):
        # G_k = P_k F^T (P^-_{k+1})^{-1}, solved as (P^-_{k+1})^T G_k^T = F P_k
        Gk = _T(np.linalg.solve(result.P_prior[k + 1], F @ result.P[k]))
        xs[k] = result.x[k] + _mv(Gk, xs[k + 1] - result.x_prior[k + 1])
        Ps[k] = _sym(result.P[k] + Gk @ (Ps[k + 1] - result.P_prior[k + 1]) @ _T(Gk))
        G[k] = Gk
    return SmootherResult(xs, Ps, G)

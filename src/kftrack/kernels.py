r"""The unchecked predict/update kernels: one home for the filter equations.

**No validation happens here.** The public functions (:func:`kftrack.kalman.predict`,
:func:`kftrack.kalman.update`, :func:`kftrack.ekf.ekf_update`, :func:`kftrack.ukf.ukf_update`,
:class:`kftrack.imm.IMM`, ...) validate their arguments once at the boundary, then call these
kernels, and their time loops call the kernels at every step. Call a kernel directly only with
arguments you have already checked (shapes as in :mod:`kftrack.kalman`: ``x`` ``(..., n)``,
``P`` ``(..., n, n)``, batch axes broadcasting): a wrong shape gives a NumPy error or a wrong
answer, not a message.

The kernels use matrix products (``@``), :func:`matrix_transpose`, ``linalg.solve``,
``linalg.slogdet``, ``linalg.cholesky`` and elementwise arithmetic, all in the array API
standard, so that they can later run on another array namespace (JAX under ``jit``). A few
NumPy-only spellings remain where replacing them could change the last bit of a result that the
book's stored outputs depend on: ``einsum`` for weighted sums (``vecdot``/``tensordot``
would be the array-API spelling) and in-place assignment of the angle components.

Equations (Bar-Shalom, Li & Kirubarajan 2001, §5.2, §10.3; Wan & van der Merwe 2000;
Blom & Bar-Shalom 1988):

.. math::

    x^- = F x,\quad P^- = F P F^\top + Q;\qquad
    S = H P H^\top + R,\quad K = P H^\top S^{-1},\quad x^+ = x + K(z - Hx),

    P^+ = (I - KH) P (I - KH)^\top + K R K^\top \;\text{(Joseph)}\quad\text{or}\quad (I - KH) P.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = [
    "Update", "SigmaPoints", "mv", "matrix_transpose", "sym", "wrap_angle", "residual", "wrap_state",
    "kf_predict", "kf_update", "innovation_score", "gain_update", "ekf_predict", "ekf_update",
    "sigma_points", "weighted_mean", "moments", "unscented", "ukf_predict", "ukf_update",
    "logsumexp", "moment_match", "mixing_log_weights", "run_sequence",
]

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


class SigmaPoints(NamedTuple):
    """Sigma points ``X`` ``(..., 2n+1, n)`` with mean weights ``Wm`` and covariance weights ``Wc`` ``(2n+1,)``."""

    X: np.ndarray
    Wm: np.ndarray
    Wc: np.ndarray


# --------------------------------------------------------------------------------------------
# small linear-algebra helpers
# --------------------------------------------------------------------------------------------
def mv(A, v):
    """Matrix times vector over batch axes: ``(..., r, c) @ (..., c) -> (..., r)``."""
    return (A @ v[..., None])[..., 0]


def matrix_transpose(A):
    """Swap the last two axes (``array_api.matrix_transpose``)."""
    return np.swapaxes(A, -1, -2)


def sym(A):
    """Symmetric part :math:`(A + A^\\top)/2`."""
    return 0.5 * (A + matrix_transpose(A))


_T = matrix_transpose


def wrap_angle(a) -> np.ndarray:
    r"""Wrap angles (rad) to :math:`(-\pi, \pi]`: :math:`\pi - ((\pi - a) \bmod 2\pi)`.

    ``wrap_angle(pi) == pi`` and ``wrap_angle(-pi) == pi``; any shape.
    """
    a = np.asarray(a, dtype=float)
    return np.pi - np.mod(np.pi - a, 2.0 * np.pi)


def residual(a, b, angles: tuple[int, ...]):
    """``a - b`` with the components ``angles`` (already validated indices) wrapped to (-pi, pi]."""
    d = a - b
    if angles:
        d = d.copy()
        d[..., angles] = wrap_angle(d[..., angles])
    return d


def wrap_state(x, x_angles):
    """Wrap the state components ``x_angles`` to (-pi, pi] (a copy; ``x`` itself when there are none)."""
    if not x_angles:
        return x
    x = np.array(x, dtype=float)
    x[..., x_angles] = wrap_angle(x[..., x_angles])
    return x


# --------------------------------------------------------------------------------------------
# linear Kalman filter
# --------------------------------------------------------------------------------------------
def kf_predict(x, P, F, Q):
    r"""Time update :math:`x^- = F x`, :math:`P^- = \operatorname{sym}(F P F^\top + Q)`."""
    return mv(F, x), sym(F @ P @ _T(F) + Q)


def innovation_score(y, S) -> tuple[np.ndarray, np.ndarray]:
    r"""NIS :math:`y^\top S^{-1} y` and Gaussian log-likelihood :math:`\log N(y; 0, S)` of an innovation."""
    Sinv_y = np.linalg.solve(S, y[..., None])[..., 0]
    nis = np.einsum("...i,...i->...", y, Sinv_y)
    _, logdet = np.linalg.slogdet(S)
    return nis, -0.5 * (nis + logdet + y.shape[-1] * _LOG_2PI)


def kf_update(x, P, z, H, R, form: str = "joseph") -> Update:
    """Measurement update with the Joseph form (``form="joseph"``, symmetrized) or the short form
    :math:`(I - KH)P` as computed (``form="standard"``, not symmetrized)."""
    y = z - mv(H, x)
    PHt = P @ _T(H)
    S = sym(H @ PHt + R)
    K = _T(np.linalg.solve(S, _T(PHt)))  # S symmetric: K^T = S^{-1} H P
    x_post = x + mv(K, y)
    I_KH = np.eye(x.shape[-1]) - K @ H
    if form == "joseph":
        P_post = sym(I_KH @ P @ _T(I_KH) + K @ R @ _T(K))
    else:  # "standard": the short form (I - KH) P, as computed (not symmetrized)
        P_post = I_KH @ P
    return Update(x_post, P_post, y, S, K, *innovation_score(y, S))


# --------------------------------------------------------------------------------------------
# extended Kalman filter
# --------------------------------------------------------------------------------------------
def gain_update(x, P, y, H, R) -> Update:
    """Update with a given innovation ``y``. Runs :func:`kf_update` linearized at zero (where its
    innovation is ``y`` exactly) and shifts the mean back by ``x``; every number is then the one
    the Kalman filter computes, to the last bit."""
    u = kf_update(np.zeros_like(x), P, y, H, R)
    return u._replace(x=x + u.x)


def ekf_predict(x, P, f, F_jac, Q, x_angles=()):
    r"""EKF time update :math:`x^- = f(x)`, :math:`P^- = F P F^\top + Q`, :math:`F = F_{jac}(x)`."""
    F = F_jac(x)
    _, P_pred = kf_predict(x, P, F, Q)
    return wrap_state(f(x), x_angles), P_pred


def ekf_update(x, P, z, h, H_jac, R, angles, x_angles=()) -> Update:
    r"""EKF update with innovation :math:`z \ominus h(x)` and :math:`H = H_{jac}(x)` (Joseph form)."""
    y = residual(z, h(x), angles)
    u = gain_update(x, P, y, H_jac(x), R)
    return u._replace(x=wrap_state(u.x, x_angles)) if x_angles else u


# --------------------------------------------------------------------------------------------
# unscented transform and filter
# --------------------------------------------------------------------------------------------
def sigma_points(x, P, c, Wm, Wc) -> SigmaPoints:
    r"""Points :math:`x`, :math:`x \pm [\sqrt{cP}]_i` (columns of the lower Cholesky factor)."""
    L = np.linalg.cholesky(c * P)  # lower: columns are the offsets
    offsets = _T(L)  # (..., n, n), row i = column i of L
    zero = np.zeros(offsets.shape[:-2] + (1, x.shape[-1]))
    X = x[..., None, :] + np.concatenate([zero, offsets, -offsets], axis=-2)
    return SigmaPoints(X, Wm, Wc)


def weighted_mean(Y, Wm, angles: tuple[int, ...]):
    """Weighted mean of points ``Y`` ``(..., 2n+1, d)``; circular mean on the ``angles`` components."""
    y = np.einsum("i,...id->...d", Wm, Y)
    if angles:
        a = Y[..., angles]
        y[..., angles] = np.arctan2(np.einsum("i,...id->...d", Wm, np.sin(a)),
                                    np.einsum("i,...id->...d", Wm, np.cos(a)))
    return y


def moments(Y, Wm, Wc, angles):
    """``(mean, cov, deviations)`` of weighted points ``Y`` (wrapped deviations on ``angles``)."""
    y = weighted_mean(Y, Wm, angles)
    dY = residual(Y, y[..., None, :], angles)
    return y, sym(np.einsum("i,...id,...ie->...de", Wc, dY, dY)), dY


def unscented(fn, x, P, points, x_angles, y_angles):
    """The unscented transform of ``N(x, P)`` through ``fn`` with the weights of ``points``
    (an object with ``weights(n) -> (Wm, Wc, c)``). Returns ``(mean, cov, cross, sigma)``."""
    n = x.shape[-1]
    Wm, Wc, c = points.weights(n)
    sp = sigma_points(x, P, c, Wm, Wc)
    Y = fn(sp.X)
    y, C, dY = moments(Y, Wm, Wc, y_angles)
    dX = residual(sp.X, x[..., None, :], x_angles)
    cross = np.einsum("i,...id,...ie->...de", Wc, dX, dY)
    return y, C, cross, sp


def ukf_predict(x, P, f, Q, points, x_angles):
    """UKF time update: unscented moments of ``f`` plus ``Q``."""
    mean, cov, _, _ = unscented(f, x, P, points, x_angles, x_angles)
    return mean, sym(cov + Q)


def ukf_update(x, P, z, h, R, points, x_angles, z_angles) -> Update:
    r"""UKF update: :math:`S = P_{zz} + R`, :math:`K = P_{xz} S^{-1}`, :math:`P^+ = P - K S K^\top`."""
    zhat, Pzz, cross, _ = unscented(h, x, P, points, x_angles, z_angles)
    S = sym(Pzz + R)
    y = residual(z, zhat, z_angles)
    K = _T(np.linalg.solve(S, _T(cross)))  # K = Pxz S^{-1}, S symmetric
    x_post = wrap_state(x + (K @ y[..., None])[..., 0], x_angles)
    P_post = sym(P - K @ S @ _T(K))
    return Update(x_post, P_post, y, S, K, *innovation_score(y, S))


# --------------------------------------------------------------------------------------------
# multiple models: mixing
# --------------------------------------------------------------------------------------------
def logsumexp(a, axis: int, keepdims: bool = False):
    """log(sum(exp(a))) along ``axis``, shifted by the maximum; all ``-inf`` gives ``-inf``."""
    m = np.max(a, axis=axis, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    with np.errstate(divide="ignore"):
        out = np.log(np.sum(np.exp(a - m), axis=axis, keepdims=True)) + m
    return out if keepdims else np.squeeze(out, axis=axis)


def moment_match(w, xs, Ps):
    r"""Moment-matched Gaussian of a mixture: ``w`` (..., r), ``xs`` (r, ..., n), ``Ps`` (r, ..., n, n)
    -> :math:`\bar x = \sum w_i x_i`, :math:`\bar P = \sum w_i [P_i + (x_i - \bar x)(x_i - \bar x)^\top]`."""
    wr = np.moveaxis(w, -1, 0)
    x = np.einsum("r...,r...i->...i", wr, xs)
    d = xs - x
    P = np.einsum("r...,r...ij->...ij", wr, Ps + d[..., :, None] * d[..., None, :])
    return x, sym(P)


def mixing_log_weights(log_mu, Pi):
    r"""IMM mixing in log space: ``log mu_{i|j}`` (..., r_i, r_j) and ``log cbar_j`` (..., r_j),
    :math:`\bar c_j = \sum_i \Pi_{ij}\mu_i`, :math:`\mu_{i|j} = \Pi_{ij}\mu_i/\bar c_j`. A mode ``j``
    that cannot be reached (:math:`\bar c_j = 0`) keeps its own estimate (weight 1 on itself)."""
    r = Pi.shape[-1]
    with np.errstate(divide="ignore"):
        logPi = np.log(Pi)
    joint = log_mu[..., :, None] + logPi  # (..., i, j)
    log_cbar = logsumexp(joint, axis=-2)
    with np.errstate(invalid="ignore"):
        logw = joint - log_cbar[..., None, :]
    dead = np.isneginf(log_cbar)
    if np.any(dead):
        eye = np.where(np.eye(r, dtype=bool), 0.0, -np.inf)
        logw = np.where(dead[..., None, :], eye, logw)
    return logw, log_cbar


# --------------------------------------------------------------------------------------------
# the NumPy time-loop driver
# --------------------------------------------------------------------------------------------
def run_sequence(zs, x0, P0, batch, row_missing, predict, update, progress: bool = False):
    """The time loop of every whole-sequence filter (the NumPy engine): at step ``k`` update with
    ``zs[k]`` (unless the row is missing), then predict. ``predict(x, P) -> (x, P)``,
    ``update(x, P, z) -> Update`` are kernels with their parameters bound; ``progress`` shows a
    tqdm bar. Returns a :class:`kftrack.kalman.FilterResult`."""
    from .kalman import FilterResult  # the result type lives with the public filter

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

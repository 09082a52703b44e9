r"""NIS-based manoeuvre detection and process-noise adaptation (chapter 9).

A filter tuned for straight flight sees a manoeuvre as a run of large normalized innovations
squared (NIS). For a consistent filter the NIS values are independent :math:`\chi^2_m`, so the
sum over a sliding window of the last :math:`w` steps,

.. math::

    s_k = \sum_{j = k - w + 1}^{k} \epsilon_{\nu,j} \;\sim\; \chi^2_{w m},

crosses its upper :math:`\chi^2_{wm}` quantile with probability ``1 - confidence`` at each step
(the false-alarm rate). :func:`detect_manoeuvre` applies this test to a NIS sequence;
:func:`adaptive_q_filter` is the Kalman filter that reacts to it by multiplying ``Q`` by a
factor ``boost`` for the next prediction while the test fires: the noise-level switching of
Bar-Shalom, Li & Kirubarajan (2001), §11.2. It is a hard, delayed, hand-tuned switch
(window, confidence, boost); the interacting multiple model estimator (:mod:`kftrack.imm`)
is the principled version that weighs the models by their likelihoods at every step.

In the first ``w - 1`` steps the window holds the steps available so far (and the threshold
their :math:`\chi^2` quantile); steps without a measurement (NaN NIS) are left out of the sum
and of its degrees of freedom.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import stats

from ._validate import as_float_array, as_matrix, broadcast_batch, check_sequence
from .engines import run_sequence
from .kernels import kf_predict, kf_update

__all__ = ["NISDetection", "detect_manoeuvre", "AdaptiveResult", "adaptive_q_filter", "innovation_autocorrelation"]


def _check_window(window, confidence, dof) -> tuple[int, float, int]:
    if isinstance(window, bool) or int(window) != window or window < 1:
        raise ValueError(f"window must be a positive integer number of steps, got {window!r}")
    if not 0.0 < float(confidence) < 1.0:
        raise ValueError(f"confidence must lie strictly between 0 and 1 (one-sided test), got {confidence!r}")
    if isinstance(dof, bool) or int(dof) != dof or dof < 1:
        raise ValueError(f"dof must be a positive integer (measurement dimension m), got {dof!r}")
    return int(window), float(confidence), int(dof)


class NISDetection(NamedTuple):
    """Sliding-window NIS test, time first.

    Attributes
    ----------
    statistic : (T, ...) windowed NIS sum :math:`s_k`.
    threshold : (T, ...) its upper :math:`\\chi^2` quantile (degrees of freedom: ``dof`` times
        the number of measured steps in the window).
    detected : (T, ...) bool, ``statistic > threshold``.
    """

    statistic: np.ndarray
    threshold: np.ndarray
    detected: np.ndarray


def _windowed(nis: np.ndarray, window: int, confidence: float, dof: int) -> NISDetection:
    have = ~np.isnan(nis)
    c = np.cumsum(np.where(have, nis, 0.0), axis=0)
    n = np.cumsum(have, axis=0)
    c_lag = np.concatenate([np.zeros((window,) + nis.shape[1:]), c[:-window]])[: len(nis)]
    n_lag = np.concatenate([np.zeros((window,) + nis.shape[1:], int), n[:-window]])[: len(nis)]
    s, cnt = c - c_lag, n - n_lag
    thr = np.where(cnt > 0, stats.chi2.ppf(confidence, np.maximum(cnt, 1) * dof), np.inf)
    return NISDetection(s, thr, s > thr)


def detect_manoeuvre(nis, dof: int, window: int = 5, confidence: float = 0.99) -> NISDetection:
    r"""Flag the steps where the NIS summed over the last ``window`` steps exceeds its
    :math:`\chi^2_{w\,m}` quantile at ``confidence`` (one-sided).

    Parameters
    ----------
    nis : (T, ...) normalized innovations squared, time first (NaN: no measurement).
    dof : measurement dimension ``m`` (degrees of freedom of one NIS value).
    window : number of steps ``w`` in the sliding sum (1 tests each step alone).
    confidence : probability that a consistent filter stays below the threshold at one step;
        ``1 - confidence`` is the false-alarm rate per step.

    Returns
    -------
    NISDetection
        ``(statistic, threshold, detected)``, each ``(T, ...)``.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.adaptive import detect_manoeuvre
    >>> nis = np.r_[np.ones(20), np.full(5, 30.0)]     # NIS of a 1-D measurement; a manoeuvre from step 20
    >>> det = detect_manoeuvre(nis, dof=1, window=3, confidence=0.99)
    >>> np.nonzero(det.detected)[0]
    array([20, 21, 22, 23, 24])
    >>> print(np.round(det.threshold[-1], 4))         # chi-square(3) quantile at 0.99
    11.3449
    """
    window, confidence, dof = _check_window(window, confidence, dof)
    v = as_float_array(nis, "nis")
    if v.ndim < 1 or v.shape[0] < 1:
        raise ValueError(f"nis must have shape (T, ...) with T >= 1 steps, got shape {v.shape}")
    if np.isinf(v).any() or (v < 0).any():
        raise ValueError("nis must hold non-negative finite values (NaN for steps without a measurement)")
    return _windowed(v, window, confidence, dof)


class AdaptiveResult(NamedTuple):
    """An adaptive-Q filter run, time first: the fields of :class:`kftrack.kalman.FilterResult`
    plus ``detected`` ``(T, ...)``, whether the NIS test fired after step ``k`` (so that the
    prediction from ``k`` to ``k + 1`` used ``boost * Q``)."""

    x_prior: np.ndarray
    P_prior: np.ndarray
    x: np.ndarray
    P: np.ndarray
    nis: np.ndarray
    loglik: np.ndarray
    detected: np.ndarray


def adaptive_q_filter(zs, x0, P0, F, Q, H, R, *, window: int = 3, confidence: float = 0.99,
                      boost: float = 10.0) -> AdaptiveResult:
    r"""Kalman filter with NIS-triggered process-noise switching (Bar-Shalom et al. 2001, §11.2).

    After the update at step :math:`k`, the windowed NIS test of :func:`detect_manoeuvre` is
    applied to the NIS values so far; where it fires, the prediction to step :math:`k + 1` uses
    :math:`\text{boost}\cdot Q` instead of :math:`Q`:

    .. math::

        P^-_{k+1} = F P_k F^\top + \big(1 + (\text{boost} - 1)\,[s_k > \chi^2_{wm,\,\text{conf}}]\big)\, Q .

    With ``boost = 1`` it is :func:`kftrack.kalman.kalman_filter` to the last bit.

    Parameters
    ----------
    zs, x0, P0, F, Q, H, R : as in :func:`kftrack.kalman.kalman_filter` (``zs`` ``(T, ..., m)``,
        ``x0`` ``(..., n)``, ``P0``, ``Q`` ``(..., n, n)``, ``F`` ``(n, n)``, ``H`` ``(m, n)``,
        ``R`` ``(..., m, m)``); every batch axis broadcasts, so one call filters many runs.
    window : steps in the NIS sum.
    confidence : one-sided level of the test; ``1 - confidence`` is the per-step false-alarm rate.
    boost : factor (>= 1) on ``Q`` while the test fires.

    Returns
    -------
    AdaptiveResult
    """
    zs, x0, P0, Q, R, n, m, batch, row_missing = check_sequence(zs, x0, P0, Q, R)
    window, confidence, m = _check_window(window, confidence, m)
    boost_f = float(boost)
    if not np.isfinite(boost_f) or boost_f < 1.0:
        raise ValueError(f"boost must be a finite factor >= 1 on Q, got {boost!r}")
    F = as_matrix(F, "F", n, n, origin=f"n = {n} from x0")
    H = as_matrix(H, "H", m, n, origin=f"m = {m} from zs, n = {n} from x0")
    batch = broadcast_batch({"zs, x0, P0, Q, R": batch, "F": F.shape[:-2], "H": H.shape[:-2]})
    T = zs.shape[0]
    nis_hist = np.full((T,) + batch, np.nan)
    flags = np.zeros((T,) + batch, bool)
    step = [0]
    Qb = boost_f * Q

    def update(x, P, z):
        upd = kf_update(x, P, z, H, R)
        nis_hist[step[0]] = upd.nis
        return upd

    def predict(x, P):
        k = step[0]
        gone = np.broadcast_to(row_missing[k], batch)
        nis_hist[k] = np.where(gone, np.nan, nis_hist[k])
        lo = max(0, k + 1 - window)
        fired = _windowed(nis_hist[lo:k + 1], window, confidence, m).detected[-1]
        flags[k] = fired
        step[0] += 1
        if boost_f == 1.0 or not fired.any():
            return kf_predict(x, P, F, Q)
        return kf_predict(x, P, F, np.where(fired[..., None, None], Qb, Q))

    # the NumPy engine with the kernels bound in closures, one covariance per run
    res = run_sequence(zs, row_missing, x0, P0, tuple(batch), tuple(batch), predict, update)
    return AdaptiveResult(*res, flags)


def innovation_autocorrelation(y, S, lag: int = 1, skip: int = 0) -> tuple[float, float]:
    r"""Lag-``lag`` autocorrelation of the whitened innovations, pooled over runs and components
    (the whiteness test of Bar-Shalom, Li & Kirubarajan 2001, §5.4.2).

    With :math:`e_k = L_k^{-1} y_k`, :math:`S_k = L_k L_k^\top`,

    .. math::

        \hat\rho = \frac{\sum_{k, i} e_k^\top e_{k+\ell}}{\sqrt{\sum e_k^\top e_k \,\sum e_{k+\ell}^\top e_{k+\ell}}},

    the sums over the steps ``skip <= k < T - lag`` and the runs. For a consistent filter the
    innovations are white and :math:`\hat\rho` is approximately normal with mean 0 and standard
    error :math:`1/\sqrt{M m}`, ``M`` the number of pairs (steps times runs): returned as ``se``.
    A gain too small (``Q`` too small or ``R`` too large) makes consecutive innovations share
    the filter's lag: :math:`\hat\rho > 0`; a gain too large makes it negative.

    Parameters
    ----------
    y : (T, ..., m) innovations, time first.
    S : (T, ..., m, m) their covariances (as the filter states them).
    lag : positive integer lag in steps.
    skip : initial steps to leave out (the transient of the initialization).

    Returns
    -------
    rho, se : float, float
    """
    y = as_float_array(y, "y")
    S = as_float_array(S, "S")
    if y.ndim < 2 or S.shape != y.shape + y.shape[-1:]:
        raise ValueError(f"y must be (T, ..., m) and S (T, ..., m, m) to match; got shapes {y.shape} and {S.shape}")
    T = y.shape[0]
    if isinstance(lag, bool) or int(lag) != lag or lag < 1:
        raise ValueError(f"lag must be a positive integer, got {lag!r}")
    if isinstance(skip, bool) or int(skip) != skip or skip < 0 or skip + lag >= T:
        raise ValueError(f"skip must be an integer with 0 <= skip < T - lag = {T - lag}, got {skip!r}")
    L = np.linalg.cholesky(S)
    e = np.linalg.solve(L, y[..., None])[..., 0]
    a, b = e[skip:T - lag], e[skip + lag:]
    rho = float(np.sum(a * b) / np.sqrt(np.sum(a * a) * np.sum(b * b)))
    return rho, float(1.0 / np.sqrt(a.size))

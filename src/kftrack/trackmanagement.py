r"""Track management: starting a track from a few measurements, M-of-N confirmation and
deletion, a sequential track score, and the false-track and lost-track rates.

* **Initiation** (Bar-Shalom, Willett & Tian 2011, §3.2): a least-squares constant-velocity fit
  through ``k >= 2`` position measurements ``dt`` apart gives the state at the last scan and its
  exact covariance; ``k = 2`` is the two-point differencing
  :math:`x = [z_2, (z_2 - z_1)/T]`, :math:`P = [[R, R/T], [R/T, 2R/T^2]]` per axis.
* **M-of-N logic**: a tentative track is confirmed once ``M`` of its last ``N`` scans hold a
  gated measurement. With independent hits of probability :math:`p` the chance of at least
  ``M`` in ``N`` scans is :math:`\sum_{k=M}^{N}\binom Nk p^k(1-p)^{N-k}`.
* **Track score** (Blackman & Popoli 1999, §6.2): the log-likelihood ratio of "target" against
  "clutter", increments :math:`\log(P_D N(\nu;0,S)/\lambda)` for a hit and
  :math:`\log(1 - P_D P_G)` for a miss, with Wald's thresholds
  :math:`\log((1-\beta)/\alpha)` (confirm) and :math:`\log(\beta/(1-\alpha))` (delete).

States are interleaved by axis, ``[x, vx, y, vy]``.
"""
from __future__ import annotations

import numpy as np
from scipy.stats import binom

from ._validate import as_float_array, as_vector, check_covariance

__all__ = ["lsq_initiation", "two_point_initiation", "three_point_initiation", "m_of_n_probability",
           "m_of_n_confirm", "score_increment", "sprt_thresholds", "lost_track"]


def lsq_initiation(zs, dt: float, R) -> tuple[np.ndarray, np.ndarray]:
    r"""Constant-velocity state at the last of ``k`` scans by least squares, with its covariance.

    Parameters
    ----------
    zs : (k, ..., d) positions at times ``-(k-1) dt, ..., -dt, 0`` (time first), ``k >= 2``.
    dt : scan interval (s), > 0.
    R : (d, d) position-noise covariance.

    Returns
    -------
    x : (..., 2d) state ``[x, vx, y, vy, ...]`` at the last scan; ``P`` (2d, 2d) its covariance
        :math:`(A^\top A)^{-1}\otimes R`, exact for white measurement noise and no process noise.
    """
    zs = as_vector(zs, "zs")
    k, d = zs.shape[0], zs.shape[-1]
    if zs.ndim < 2 or k < 2:
        raise ValueError(f"zs must have shape (k, ..., d) with k >= 2 scans, got shape {zs.shape}")
    dt = float(dt)
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be > 0 (s), got {dt!r}")
    R = check_covariance(R, "R", d, positive_definite=True, origin=f"d = {d} from zs")
    t = dt * np.arange(-(k - 1), 1)
    A = np.stack([np.ones(k), t], axis=1)
    G = np.linalg.inv(A.T @ A)
    coef = np.einsum("ab,kb,k...d->...ad", G, A, zs)  # (..., 2, d): [position, velocity]
    x = np.swapaxes(coef, -1, -2).reshape(coef.shape[:-2] + (2 * d,))
    P = np.kron(R, G)  # interleaved order: block (i, j) of R times G
    return x, 0.5 * (P + P.T)


def two_point_initiation(z1, z2, dt: float, R):
    """Two-point differencing; see :func:`lsq_initiation` (``k = 2``).

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.trackmanagement import two_point_initiation
    >>> x, P = two_point_initiation([0.0, 0.0], [10.0, 5.0], dt=1.0, R=np.eye(2))
    >>> print(x)                                      # [x, vx, y, vy] at the second scan
    [10. 10.  5.  5.]
    >>> print(np.round(P, 6))                         # per axis R [[1, 1/T], [1/T, 2/T²]]
    [[1. 1. 0. 0.]
     [1. 2. 0. 0.]
     [0. 0. 1. 1.]
     [0. 0. 1. 2.]]
    """
    return lsq_initiation(np.stack([as_vector(z1, "z1"), as_vector(z2, "z2")]), dt, R)


def three_point_initiation(z1, z2, z3, dt: float, R):
    r"""Three-point least-squares start: position :math:`(-z_1 + 2z_2 + 5z_3)/6`, velocity
    :math:`(z_3 - z_1)/(2T)`, covariance per axis :math:`R\,[[5/6, 1/(2T)], [1/(2T), 1/(2T^2)]]`."""
    return lsq_initiation(np.stack([as_vector(z1, "z1"), as_vector(z2, "z2"), as_vector(z3, "z3")]), dt, R)


def _check_mn(M, N):
    if int(M) != M or int(N) != N or not 1 <= M <= N:
        raise ValueError(f"M and N must be integers with 1 <= M <= N (M-of-N logic), got M = {M!r}, N = {N!r}")
    return int(M), int(N)


def m_of_n_probability(p, M: int, N: int) -> np.ndarray:
    r"""Probability of at least ``M`` hits in ``N`` independent scans of hit probability ``p``:
    :math:`\sum_{k=M}^{N}\binom Nk p^k (1-p)^{N-k}`.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.trackmanagement import m_of_n_probability
    >>> print(np.round(m_of_n_probability(0.9, M=2, N=3), 6))   # 3 p² (1 - p) + p³
    0.972
    """
    M, N = _check_mn(M, N)
    p = as_float_array(p, "p")
    if np.any((p < 0) | (p > 1)):
        raise ValueError(f"p (hit probability) must lie in [0, 1], got {p!r}")
    return binom.sf(M - 1, N, p)


def m_of_n_confirm(hits, M: int, N: int) -> np.ndarray:
    """First scan at which ``M`` of the last ``N`` scans were hits.

    Parameters
    ----------
    hits : (K, ...) bool, scan first.

    Returns
    -------
    (...) int: the scan index of confirmation, or -1 if never (within ``K`` scans). For
    deletion, pass ``~hits`` (``M`` misses among the last ``N``).

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.trackmanagement import m_of_n_confirm
    >>> print(m_of_n_confirm(np.array([True, False, False, True, True]), M=2, N=3))   # scan index
    4
    """
    M, N = _check_mn(M, N)
    h = np.asarray(hits)
    if h.dtype != bool:
        raise TypeError(f"hits must be a boolean array (scan first), got dtype {h.dtype}")
    c = np.cumsum(h, axis=0, dtype=int)
    c = np.concatenate([np.zeros((1,) + h.shape[1:], dtype=int), c])
    window = c[1:] - c[np.maximum(np.arange(1, h.shape[0] + 1) - N, 0)]
    ok = window >= M
    return np.where(ok.any(0), np.argmax(ok, axis=0), -1)


def score_increment(hit, logN, *, P_D: float, P_G: float, clutter_density) -> np.ndarray:
    r"""Track-score (log-likelihood-ratio) increment of one scan: :math:`\log(P_D/\lambda) + \log N`
    for a hit with Gaussian log-likelihood ``logN``, :math:`\log(1 - P_D P_G)` for a miss."""
    P_D, P_G = float(as_float_array(P_D, "P_D")), float(as_float_array(P_G, "P_G"))
    if not 0 < P_D <= 1:
        raise ValueError(f"P_D (detection probability) must lie in (0, 1], got {P_D!r}")
    if not 0 < P_G < 1:
        raise ValueError(f"P_G (gate probability) must lie in (0, 1), got {P_G!r}")
    lam = as_float_array(clutter_density, "clutter_density")
    if np.any(lam <= 0):
        raise ValueError(f"clutter_density must be > 0, got {clutter_density!r}")
    hit = np.asarray(hit, dtype=bool)
    return np.where(hit, np.log(P_D) - np.log(lam) + np.where(hit, logN, 0.0), np.log1p(-P_D * P_G))


def sprt_thresholds(alpha: float, beta: float) -> tuple[float, float]:
    r"""Wald's thresholds on the track score: confirm above :math:`\log((1-\beta)/\alpha)`,
    delete below :math:`\log(\beta/(1-\alpha))`; ``alpha`` = false-confirmation and ``beta`` =
    true-track-deletion probabilities."""
    if not (0 < alpha < 1 and 0 < beta < 1 and alpha + beta < 1):
        raise ValueError(f"alpha and beta must lie in (0, 1) with alpha + beta < 1, got {alpha!r}, {beta!r}")
    return float(np.log((1 - beta) / alpha)), float(np.log(beta / (1 - alpha)))


def lost_track(error, threshold: float, consecutive: int = 3) -> np.ndarray:
    """A track is lost once its position error exceeds ``threshold`` on ``consecutive`` scans in
    a row. ``error`` (T, ...) scan first; returns (...) bool."""
    e = as_float_array(error, "error")
    if not threshold > 0:
        raise ValueError(f"threshold must be > 0, got {threshold!r}")
    return m_of_n_confirm(e > threshold, consecutive, consecutive) >= 0

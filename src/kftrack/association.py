r"""Measurement-to-track association in clutter: validation gates, nearest and strongest
neighbour, the probabilistic data association filter (PDAF) and IMM-PDAF, and, for several
targets, global nearest neighbour (GNN), joint PDA (JPDA) and the GOSPA/OSPA metrics.

A **scan** holds a variable number of measurements. To filter many Monte Carlo runs at once
the scans are **padded**: ``Z`` has shape ``(..., M_max, m)`` and a boolean ``mask``
``(..., M_max)`` marks the real measurements (padding entries may hold anything finite; they are
never used). Every single-target function broadcasts over the leading axes ``...`` with no
Python loop over runs.

Equations (Bar-Shalom & Tse 1975; Bar-Shalom, Daum & Huang 2009; Bar-Shalom, Willett & Tian
2011, ch. 3 and 6), with predicted measurement :math:`\hat z = Hx`, innovations
:math:`\nu_i = z_i - \hat z`, :math:`S = HPH^\top + R`, :math:`K = PH^\top S^{-1}`:

* gate: :math:`d_i^2 = \nu_i^\top S^{-1}\nu_i \le \gamma`, :math:`\gamma = \chi^2_m{}^{-1}(P_G)`,
  of volume :math:`V = c_m\,|\gamma S|^{1/2}`, :math:`c_m = \pi^{m/2}/\Gamma(m/2+1)`;
* association probabilities, for the ``m_k`` gated measurements,
  :math:`\beta_i = L_i / (1 - P_D P_G + \sum_j L_j)`, :math:`\beta_0 = (1 - P_D P_G)/(\dots)`,
  with :math:`L_i = P_D\,N(\nu_i; 0, S)/\lambda`; the **parametric** PDAF takes the Poisson
  clutter density :math:`\lambda` (per unit measurement volume), the **non-parametric** one
  :math:`\lambda = m_k / V`;
* update: :math:`\nu = \sum_i \beta_i\nu_i`, :math:`x^+ = x + K\nu`,
  :math:`P^+ = \beta_0 P + (1-\beta_0) P^c + K\big[\sum_i\beta_i\nu_i\nu_i^\top - \nu\nu^\top\big]K^\top`,
  where :math:`P^c` is the Kalman (Joseph-form) posterior covariance and the bracket is the
  **spread of the innovations**.

The state order follows the package (``[x, vx, y, vy]``); ``H`` picks the measured components.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.special import gammaln
from scipy.stats import chi2

from . import kernels as _k
from ._validate import as_float_array, as_vector, broadcast_batch, check_covariance, check_finite
from .kalman import _overflow

__all__ = [
    "gate_threshold", "unit_ball_volume", "gate_volume", "check_scan", "Gate", "validation_gate",
    "NeighbourUpdate", "nearest_neighbour", "strongest_neighbour",
    "PDAUpdate", "pda_weights", "pdaf_update", "imm_pdaf_update",
    "gnn_assignment", "JPDAUpdate", "jpda_update", "GOSPA", "gospa", "gospa_assignment", "ospa",
    "ScanFilterResult", "filter_scans", "jpda_filter", "gnn_filter",
]

_LOG_2PI = np.log(2.0 * np.pi)


# --------------------------------------------------------------------------------------------
# argument checks
# --------------------------------------------------------------------------------------------
def _scalar(value, name: str, what: str) -> float:
    arr = as_float_array(value, name)
    if arr.ndim != 0:
        raise ValueError(f"{name} ({what}) must be a scalar, shared by the batch, got an array of shape {arr.shape}")
    return float(arr)


def _check_prob_gate(P_G) -> float:
    v = _scalar(P_G, "P_G", "gate probability")
    if not 0.0 < v < 1.0:
        raise ValueError(f"P_G (gate probability) must lie in the open interval (0, 1), got {P_G!r}")
    return v


def _check_prob_detect(P_D) -> float:
    v = _scalar(P_D, "P_D", "detection probability")
    if not 0.0 < v <= 1.0:
        raise ValueError(f"P_D (detection probability) must lie in (0, 1], got {P_D!r}")
    return v


def _check_density(clutter_density):
    """``None`` (non-parametric) or an array ``>= 0`` broadcasting over the batch axes."""
    if clutter_density is None:
        return None
    lam = as_float_array(clutter_density, "clutter_density")
    if not np.all(np.isfinite(lam)) or np.any(lam < 0):
        raise ValueError("clutter_density (Poisson false alarms per unit measurement volume) must be finite "
                         f"and >= 0, got {clutter_density!r}")
    return lam


def check_scan(Z, mask=None, m: int | None = None, name: str = "Z") -> tuple[np.ndarray, np.ndarray]:
    """A padded scan ``Z`` ``(..., M_max, m)`` and its boolean ``mask`` ``(..., M_max)``.

    ``mask`` defaults to all true (every row a measurement). Padding rows (mask false) are set to
    zero in the returned copy so they cannot produce NaN downstream.
    """
    Z = as_float_array(Z, name)
    if Z.ndim < 2:
        raise ValueError(f"{name} must have shape (..., M_max, m) (a padded set of measurements), got shape {Z.shape}")
    if m is not None and Z.shape[-1] != m:
        raise ValueError(f"{name} must have shape (..., M_max, {m}) (measurements of width m = {m} from H), "
                         f"got shape {Z.shape}")
    if mask is None:
        mask = np.ones(Z.shape[:-1], dtype=bool)
    else:
        mask = np.asarray(mask)
        if mask.dtype != bool:
            raise TypeError(f"mask must be a boolean array (True = real measurement), got dtype {mask.dtype}")
        try:
            mask = np.broadcast_to(mask, Z.shape[:-1])
        except ValueError:
            raise ValueError(f"mask must have shape {Z.shape[:-1]} (the leading axes of {name}), "
                             f"got shape {mask.shape}") from None
    if not np.all(np.isfinite(Z[mask])):
        raise ValueError(f"{name} must be finite where mask is true")
    return np.where(mask[..., None], Z, 0.0), mask


# --------------------------------------------------------------------------------------------
# the validation gate
# --------------------------------------------------------------------------------------------
def gate_threshold(P_G: float, m: int) -> float:
    r"""Threshold :math:`\gamma` with :math:`P\{\chi^2_m \le \gamma\} = P_G`."""
    P_G = _check_prob_gate(P_G)
    if int(m) != m or m < 1:
        raise ValueError(f"m (measurement dimension) must be a positive integer, got {m!r}")
    return _gate_constants(P_G, int(m))[0]


@functools.lru_cache(maxsize=64)
def _gate_constants(P_G: float, m: int) -> tuple[float, float]:
    r"""``(gamma, c_m gamma^{m/2})`` for a checked ``P_G`` and ``m``: the threshold
    :math:`\gamma = \chi^2_m{}^{-1}(P_G)` and the factor of the gate volume
    :math:`V = c_m\gamma^{m/2}|S|^{1/2}`, computed once per ``(P_G, m)`` (``chi2.ppf`` costs
    tens of microseconds, and the gate is applied at every scan)."""
    gamma = float(chi2.ppf(P_G, m))
    return gamma, unit_ball_volume(m) * gamma ** (0.5 * m)


def unit_ball_volume(m: int) -> float:
    r"""Volume of the unit ball in :math:`\mathbb R^m`, :math:`c_m = \pi^{m/2}/\Gamma(m/2+1)`
    (2, π, 4π/3 for m = 1, 2, 3)."""
    if int(m) != m or m < 1:
        raise ValueError(f"m (dimension) must be a positive integer, got {m!r}")
    return float(np.exp(0.5 * m * np.log(np.pi) - gammaln(0.5 * m + 1.0)))


def gate_volume(S, P_G: float) -> np.ndarray:
    r"""Volume of the ellipsoidal gate :math:`V = c_m |\gamma S|^{1/2} = c_m\gamma^{m/2}|S|^{1/2}`.

    Parameters
    ----------
    S : (..., m, m) innovation covariance, positive definite.
    P_G : gate probability in (0, 1).

    Returns
    -------
    (...) gate volumes, in measurement units to the power m (m² for a planar position).
    """
    S = check_covariance(S, "S", positive_definite=True)
    m = S.shape[-1]
    _, logdet = np.linalg.slogdet(S)
    return _gate_constants(_check_prob_gate(P_G), m)[1] * np.exp(0.5 * logdet)


class Gate(NamedTuple):
    """Gating of a padded scan against one prediction (batch axes ``...``).

    Attributes
    ----------
    zhat : (..., m) predicted measurement; ``S`` (..., m, m) innovation covariance.
    nu : (..., M_max, m) innovations (zero at padding); ``d2`` (..., M_max) their squared
        Mahalanobis distances (``inf`` at padding).
    inside : (..., M_max) true for real measurements with ``d2 <= gamma``.
    gamma : the threshold; ``volume`` (...) the gate volume.
    logN : (..., M_max) Gaussian log-likelihoods ``log N(nu; 0, S)`` (``-inf`` at padding).
    """

    zhat: np.ndarray
    S: np.ndarray
    nu: np.ndarray
    d2: np.ndarray
    inside: np.ndarray
    gamma: float
    volume: np.ndarray
    logN: np.ndarray


def _gate(x, P, Z, mask, H, R, P_G):
    """Kernel of :func:`validation_gate` (no argument checks: the public functions have made
    them); also returns the covariance part ``u`` of the Kalman update
    (:func:`kftrack.kernels.kf_gain`: ``S``, ``K``, Joseph ``P``, ``log det S``), which the PDAF
    reuses. The same bits as the checked :func:`kftrack.kalman.update` (which calls the same
    kernel); like it, a ``ValueError`` if the prediction, gain or covariance overflows."""
    zhat = (H @ x[..., None])[..., 0]
    u = _k.kf_gain(P, H, R)
    if not (np.isfinite(zhat).all() and np.isfinite(u.K).all() and np.isfinite(u.P).all()):
        raise ValueError(_overflow("the predicted measurement H x, the gain or the updated covariance",
                                   x=x, P=P, H=H, R=R))
    S = u.S
    m = Z.shape[-1]
    nu = np.where(mask[..., None], Z - zhat[..., None, :], 0.0)
    Sinv_nu = np.linalg.solve(S[..., None, :, :], nu[..., None])[..., 0]
    d2 = np.where(mask, np.einsum("...i,...i->...", nu, Sinv_nu), np.inf)
    gamma, c_gamma = _gate_constants(P_G, m)
    logdet = u.logdet
    volume = c_gamma * np.exp(0.5 * logdet)
    logN = -0.5 * (d2 + (logdet + m * _LOG_2PI)[..., None])
    return Gate(zhat, S, nu, d2, mask & (d2 <= gamma), gamma, volume, logN), u


def _check_measurement(H, R, n: int, origin: str):
    """The measurement matrix ``H`` (m, n) or (..., m, n), finite, and ``R`` (m, m) or (..., m, m),
    positive definite."""
    H = as_float_array(H, "H")
    if H.ndim < 2 or H.shape[-1] != n:
        raise ValueError(f"H must have shape (m, {n}) ({origin}), got shape {H.shape}")
    check_finite(H, "H")
    m = H.shape[-2]
    return H, check_covariance(R, "R", m, positive_definite=True, origin=f"m = {m} from H")


def _check_filter_args(x, P, Z, mask, H, R):
    """The checks of the public filters, made once: then :func:`_gate` and the kernels run unchecked."""
    x = as_vector(x, "x")
    n = x.shape[-1]
    P = check_covariance(P, "P", n, origin=f"n = {n} from x")
    H, R = _check_measurement(H, R, n, f"n = {n} from x")
    broadcast_batch({"x": x.shape[:-1], "P": P.shape[:-2], "H": H.shape[:-2], "R": R.shape[:-2]})
    Z, mask = check_scan(Z, mask, H.shape[-2])
    return x, P, Z, mask, H, R


def validation_gate(x, P, Z, H, R, *, P_G: float, mask=None) -> Gate:
    r"""Ellipsoidal chi-square validation gate of probability ``P_G``.

    A measurement is validated when :math:`(z-\hat z)^\top S^{-1}(z-\hat z) \le \gamma`,
    :math:`\gamma = \chi^2_m{}^{-1}(P_G)`; a target measurement falls inside with probability
    ``P_G`` when the filter is consistent.

    Parameters
    ----------
    x : (..., n) predicted state; ``P`` (..., n, n) its covariance.
    Z : (..., M_max, m) padded measurements; ``mask`` (..., M_max) bool, default all true.
    H : (m, n) measurement matrix; ``R`` (m, m) measurement-noise covariance.
    P_G : gate probability in (0, 1).
    """
    P_G = _check_prob_gate(P_G)
    x, P, Z, mask, H, R = _check_filter_args(x, P, Z, mask, H, R)
    return _gate(x, P, Z, mask, H, R, P_G)[0]


# --------------------------------------------------------------------------------------------
# nearest and strongest neighbour
# --------------------------------------------------------------------------------------------
class NeighbourUpdate(NamedTuple):
    """Result of a nearest/strongest-neighbour update: ``x`` (..., n), ``P`` (..., n, n),
    ``index`` (...) of the chosen measurement (-1 when the gate is empty: then ``x, P`` are the
    prediction), and the :class:`Gate`."""

    x: np.ndarray
    P: np.ndarray
    index: np.ndarray
    gate: Gate


def _select_update(x, P, g, u, idx):
    has = idx >= 0
    nu = np.take_along_axis(g.nu, np.maximum(idx, 0)[..., None, None], axis=-2)[..., 0, :]
    xk = x + (u.K @ nu[..., None])[..., 0]
    x_out = np.where(has[..., None], xk, x)
    P_out = np.where(has[..., None, None], u.P, P)
    return NeighbourUpdate(x_out, P_out, idx, g)


def nearest_neighbour(x, P, Z, H, R, *, P_G: float, mask=None) -> NeighbourUpdate:
    r"""Nearest-neighbour filter: update with the gated measurement of smallest
    :math:`d^2 = \nu^\top S^{-1}\nu`, as if it were certainly the target's (Kalman update);
    an empty gate gives the prediction. Arguments as in :func:`validation_gate`."""
    P_G = _check_prob_gate(P_G)
    x, P, Z, mask, H, R = _check_filter_args(x, P, Z, mask, H, R)
    g, u = _gate(x, P, Z, mask, H, R, P_G)
    d2 = np.where(g.inside, g.d2, np.inf)
    idx = np.where(g.inside.any(-1), np.argmin(d2, axis=-1), -1)
    return _select_update(x, P, g, u, idx)


def strongest_neighbour(x, P, Z, H, R, amplitude, *, P_G: float, mask=None) -> NeighbourUpdate:
    r"""Strongest-neighbour filter: update with the gated measurement of largest signal
    ``amplitude`` (..., M_max) (e.g. the detector's power); an empty gate gives the prediction."""
    P_G = _check_prob_gate(P_G)
    x, P, Z, mask, H, R = _check_filter_args(x, P, Z, mask, H, R)
    amplitude = as_float_array(amplitude, "amplitude")
    try:
        amplitude = np.broadcast_to(amplitude, Z.shape[:-1])
    except ValueError:
        raise ValueError(f"amplitude must have shape {Z.shape[:-1]} (one value per row of Z), "
                         f"got shape {amplitude.shape}") from None
    g, u = _gate(x, P, Z, mask, H, R, P_G)
    a = np.where(g.inside, amplitude, -np.inf)
    idx = np.where(g.inside.any(-1), np.argmax(a, axis=-1), -1)
    return _select_update(x, P, g, u, idx)


# --------------------------------------------------------------------------------------------
# PDAF
# --------------------------------------------------------------------------------------------
class PDAUpdate(NamedTuple):
    """Result of a PDAF update (batch axes ``...``).

    Attributes
    ----------
    x : (..., n) posterior mean; ``P`` (..., n, n) posterior covariance.
    beta : (..., M_max + 1) association probabilities, ``beta[..., 0]`` = no gated measurement
        is the target's, ``beta[..., 1 + i]`` = measurement ``i`` is (0 outside the gate).
    gate : the :class:`Gate`.
    spread : (..., n, n) the spread-of-innovations term
        :math:`K[\\sum\\beta_i\\nu_i\\nu_i^\\top - \\nu\\nu^\\top]K^\\top`.
    loglik : (...) log of the scan's likelihood ratio against "all clutter",
        :math:`\\log(1 - P_D P_G + \\sum_i L_i)`; the mode likelihood of IMM-PDAF.
    """

    x: np.ndarray
    P: np.ndarray
    beta: np.ndarray
    gate: Gate
    spread: np.ndarray
    loglik: np.ndarray


def _logsumexp(a, axis=-1):
    amax = np.max(a, axis=axis, keepdims=True)
    amax = np.where(np.isfinite(amax), amax, 0.0)
    with np.errstate(divide="ignore"):
        return np.log(np.sum(np.exp(a - amax), axis=axis)) + amax[..., 0]


def _log_pda_terms(g: Gate, P_D, P_G, lam):
    """``log L_0 = log(1 - P_D P_G)`` and ``log L_i`` (..., M_max), ``-inf`` outside the gate.

    ``lam`` is ``None`` (non-parametric: ``m_k / V``) or an array ``>= 0``; ``lam = 0`` (no
    clutter) gives weights proportional to ``N_i`` and, when the gate holds a measurement,
    ``beta_0 = 0`` exactly."""
    mk = g.inside.sum(-1)
    if lam is None:
        with np.errstate(divide="ignore"):
            log_lam = np.log(mk) - np.log(g.volume)
    else:
        with np.errstate(divide="ignore"):
            log_lam = np.log(lam) * np.ones(mk.shape)
    zero = np.isneginf(log_lam)
    log_lam = np.where(zero, 0.0, log_lam)
    logL = np.where(g.inside, np.log(P_D) + g.logN - log_lam[..., None], -np.inf)
    with np.errstate(divide="ignore"):
        logL0 = np.log1p(-P_D * P_G) * np.ones(mk.shape)
    logL0 = np.where(zero & (mk > 0), -np.inf, logL0)
    return logL0, logL, log_lam, zero


def pda_weights(g: Gate, *, P_D: float, P_G: float, clutter_density=None) -> np.ndarray:
    r"""PDAF association probabilities :math:`(\beta_0, \beta_1, \dots)` ``(..., M_max + 1)``
    from a :class:`Gate` (see the module docstring); they sum to one."""
    P_D, P_G, lam = _check_prob_detect(P_D), _check_prob_gate(P_G), _check_density(clutter_density)
    return _pda_beta(g, P_D, P_G, lam)[0]


def _pda_beta(g, P_D, P_G, lam):
    logL0, logL, log_lam, zero = _log_pda_terms(g, P_D, P_G, lam)
    logs = np.concatenate([logL0[..., None], logL], axis=-1)
    total = _logsumexp(logs)
    beta = np.exp(logs - total[..., None])
    # likelihood ratio against all clutter; with lam = 0 the ratio is infinite: report the
    # unnormalised log of the mixture density instead (useful only for comparing modes)
    loglik = np.where(zero, _logsumexp(logs), total)
    return beta, loglik


def _pda_combine(x, P, u, nu, beta):
    """Kernel of the PDAF state update from innovations ``nu`` (..., M, m) and ``beta``
    (..., M + 1); ``u`` is the Kalman update with ``y = 0`` (``K``, Joseph ``P``)."""
    b0, b = beta[..., 0], beta[..., 1:]
    nu_c = np.einsum("...i,...ij->...j", b, nu)
    x_post = x + (u.K @ nu_c[..., None])[..., 0]
    outer = np.einsum("...i,...ij,...ik->...jk", b, nu, nu) - nu_c[..., :, None] * nu_c[..., None, :]
    spread = u.K @ outer @ np.swapaxes(u.K, -1, -2)
    P_post = b0[..., None, None] * P + (1.0 - b0)[..., None, None] * u.P + spread
    return x_post, 0.5 * (P_post + np.swapaxes(P_post, -1, -2)), spread


def pdaf_update(x, P, Z, H, R, *, P_D: float, P_G: float, clutter_density=None, mask=None) -> PDAUpdate:
    r"""Probabilistic data association filter update (Bar-Shalom & Tse 1975).

    Parameters
    ----------
    x : (..., n) predicted state; ``P`` (..., n, n) its covariance.
    Z : (..., M_max, m) padded scan; ``mask`` (..., M_max) bool (default all true).
    H : (m, n) measurement matrix; ``R`` (m, m) measurement-noise covariance.
    P_D : detection probability, a scalar in (0, 1] (shared by the batch).
    P_G : gate probability, a scalar in (0, 1).
    clutter_density : Poisson clutter density :math:`\lambda` per unit measurement volume
        (scalar or broadcasting over ``...``; ``>= 0``) for the parametric PDAF, or ``None`` for
        the non-parametric PDAF (:math:`\lambda = m_k/V`).

    Returns
    -------
    PDAUpdate
        With :math:`\lambda \to 0` and ``P_D = 1`` a single gated measurement gives exactly the
        Kalman update of :func:`kftrack.kalman.update`.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.association import pdaf_update
    >>> x, P, H, R = np.array([0.0, 1.0]), np.eye(2), np.array([[1.0, 0.0]]), np.eye(1)
    >>> Z = np.array([[0.5], [3.0], [-0.2]])          # one scan: three measurements, at most one the target's
    >>> u = pdaf_update(x, P, Z, H, R, P_D=0.9, P_G=0.99, clutter_density=0.1)
    >>> print(np.round(u.beta, 3))                    # [none is the target's, measurement 0, 1, 2]
    [0.021 0.452 0.051 0.476]
    >>> print(np.round(u.x, 4))
    [0.1415 1.    ]
    """
    P_D, P_G, lam = _check_prob_detect(P_D), _check_prob_gate(P_G), _check_density(clutter_density)
    x, P, Z, mask, H, R = _check_filter_args(x, P, Z, mask, H, R)
    g, u = _gate(x, P, Z, mask, H, R, P_G)
    beta, loglik = _pda_beta(g, P_D, P_G, lam)
    xp, Pp, spread = _pda_combine(x, P, u, g.nu, beta)
    return PDAUpdate(xp, Pp, beta, g, spread, loglik)


def imm_pdaf_update(estimator, state, Z, *, P_D: float, P_G: float, clutter_density, mask=None):
    r"""IMM-PDAF measurement update (Houles & Bar-Shalom 1989): a PDAF update in every mode,
    mode likelihoods :math:`\Lambda_j = 1 - P_D P_G + \sum_i L_{ij}` (the scan's likelihood ratio
    against "all clutter" under mode ``j``), :math:`\mu_j \propto \Lambda_j\bar c_j`.

    Parameters
    ----------
    estimator : a :class:`kftrack.imm.IMM` whose modes have linear measurements (attributes
        ``H`` and ``R``, e.g. :class:`~kftrack.imm.KalmanMode`).
    state : its :class:`~kftrack.imm.IMMState` after :meth:`~kftrack.imm.IMM.predict`.
    Z, mask : the padded scan, as in :func:`pdaf_update`.
    clutter_density : the parametric :math:`\lambda` (required: the non-parametric
        :math:`m_k/V` differs between modes and would make their likelihoods incomparable).

    Returns
    -------
    IMMState
        Built by :meth:`kftrack.imm.IMM.from_modes` (combined ``x``, ``P``, ``mu`` consistent;
        its ``loglik`` is NaN: the per-mode :math:`\log\Lambda_j` are the ``loglik`` of
        :func:`pdaf_update` in each mode).
    """
    if clutter_density is None:
        raise ValueError("clutter_density must be given (the parametric PDAF) for IMM-PDAF, got None")
    P_D, P_G, lam = _check_prob_detect(P_D), _check_prob_gate(P_G), _check_density(clutter_density)
    xs, Ps, logliks = [], [], []
    for j, mode in enumerate(estimator.modes):
        if not (hasattr(mode, "H") and hasattr(mode, "R")):
            raise TypeError(f"estimator.modes[{j}] must have a linear measurement (attributes H, R), "
                            f"got {type(mode).__name__}")
        if j == 0:
            Zc, mask = check_scan(Z, mask, mode.H.shape[0])
        g, u = _gate(state.xs[j], state.Ps[j], Zc, mask, mode.H, mode.R, P_G)
        beta, loglik = _pda_beta(g, P_D, P_G, lam)
        xp, Pp, _ = _pda_combine(state.xs[j], state.Ps[j], u, g.nu, beta)
        xs.append(xp)
        Ps.append(Pp)
        logliks.append(loglik)
    loglik = np.stack(logliks, axis=-1)
    joint = state.log_mu + loglik
    log_mu = joint - _logsumexp(joint)[..., None]
    return estimator.from_modes(xs, Ps, np.exp(log_mu))


# --------------------------------------------------------------------------------------------
# several targets: GNN and JPDA
# --------------------------------------------------------------------------------------------
def gnn_assignment(cost, gate_mask, miss_cost=None) -> np.ndarray:
    r"""Global nearest neighbour: the one-to-one assignment of tracks to gated measurements of least
    total cost, each track free to take no measurement at a price (a non-assignment cost per
    track, Blackman & Popoli 1999).

    It solves, over the assignments :math:`a` (``a[i]`` a gated measurement or -1, no measurement
    to two tracks),

    .. math:: \min_a \sum_{i:\,a_i \ge 0} C_{i a_i} + \sum_{i:\,a_i = -1} c^{\text{miss}}_i .

    Parameters
    ----------
    cost : (T, M) cost of giving measurement ``j`` to track ``i`` (e.g. ``d2 + log|S|``); finite
        where gated (ignored elsewhere).
    gate_mask : (T, M) bool, true where measurement ``j`` is in track ``i``'s gate.
    miss_cost : scalar or (T,), the cost of leaving track ``i`` without a measurement. Default:
        the gate's edge taken as the largest gated cost + 1 (0 if nothing is gated), above every
        gated cost, so a track alone with its gated measurements always takes one; a track gives
        up its measurement only when another track's gain pays for it. :func:`gnn_filter` passes
        each track's own gate edge, :math:`\gamma + \log|S_i|`.

    Returns
    -------
    (T,) int: the measurement of each track, -1 for none. Solved exactly with
    ``scipy.optimize.linear_sum_assignment`` on the (T, M + T) matrix ``[C | diag(miss_cost)]``,
    non-gated pairs and off-diagonal "miss" entries forbidden (``inf``). One problem at a time:
    ``linear_sum_assignment`` has no batch axis, so :func:`gnn_filter` calls this once per run
    and scan (a Python loop over runs, unlike the single-target functions of this module).

    Examples
    --------
    >>> gnn_assignment([[5.0, 0.0], [0.0, 10.0]], [[True, False], [True, True]]).tolist()
    [-1, 0]
    """
    cost = as_float_array(cost, "cost")
    gate_mask = np.asarray(gate_mask)
    if gate_mask.dtype != bool:
        raise TypeError(f"gate_mask must be a boolean array (True = gated pair), got dtype {gate_mask.dtype}")
    if cost.ndim != 2 or gate_mask.shape != cost.shape:
        raise ValueError(f"cost and gate_mask must both have shape (T, M), got {cost.shape} and {gate_mask.shape}")
    T, M = cost.shape
    if not np.all(np.isfinite(cost[gate_mask])):
        raise ValueError("cost must be finite where gate_mask is true")
    if miss_cost is None:
        miss = np.full(T, float(np.max(cost[gate_mask])) + 1.0 if gate_mask.any() else 0.0)
    else:
        miss = as_float_array(miss_cost, "miss_cost")
        if miss.ndim > 1 or (miss.ndim == 1 and miss.shape != (T,)):
            raise ValueError(f"miss_cost must be a scalar or have shape ({T},) (one per track), got shape {miss.shape}")
        if not np.all(np.isfinite(miss)):
            raise ValueError("miss_cost must be finite")
        miss = np.broadcast_to(miss, (T,))
    C = np.full((T, M + T), np.inf)
    C[:, :M] = np.where(gate_mask, cost, np.inf)
    C[np.arange(T), M + np.arange(T)] = miss
    rows, cols = linear_sum_assignment(C)
    out = np.full(T, -1, dtype=int)
    take = cols < M
    out[rows[take]] = cols[take]
    return out


def _gating_clusters(inside: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Gating clusters of one scan: ``inside`` (T, M) bool -> list of ``(targets, measurements)``
    index arrays, the connected parts of the graph joining a target to its gated measurements.
    Targets without a gated measurement are left out (they are missed with probability 1)."""
    A_ = inside.astype(np.int64)
    reach = (A_ @ A_.T) > 0  # targets sharing a measurement (and each gating target with itself)
    while True:  # transitive closure by squaring, at most log2(T) steps
        nxt = (reach.astype(np.int64) @ reach.astype(np.int64)) > 0
        if np.array_equal(nxt, reach):
            break
        reach = nxt
    out, seen = [], np.zeros(len(inside), dtype=bool)
    for t in np.flatnonzero(inside.any(1)):
        if not seen[t]:
            ts = np.flatnonzero(reach[t])
            seen[ts] = True
            out.append((ts, np.flatnonzero(inside[ts].any(0))))
    return out


def _count_events(adj: tuple[tuple[int, ...], ...], limit: int) -> tuple[int, bool]:
    """Number of joint events of a cluster (each target one of its gated measurements ``adj[t]``
    or none, no measurement twice), by dynamic programming over the targets on the set of
    measurements still needed later. Returns ``(count, exact)``; once the partial count (a lower
    bound) exceeds ``limit`` and the table grows past 4096 sets, ``(lower bound, False)``."""
    last = {}
    for t, js in enumerate(adj):
        for j in js:
            last[j] = t
    states = {0: 1}
    for t, js in enumerate(adj):
        new: dict[int, int] = {}
        done = sum(1 << j for j in js if last[j] == t)  # bits no later target can use: forget them
        for used, c in states.items():
            key = used & ~done
            new[key] = new.get(key, 0) + c
            for j in js:
                if not used >> j & 1:
                    key = (used | 1 << j) & ~done
                    new[key] = new.get(key, 0) + c
        states = new
        if len(states) > 4096 and sum(states.values()) > limit:
            return sum(states.values()), False
    return sum(states.values()), True


def _cluster_events(adj: tuple[tuple[int, ...], ...]) -> np.ndarray:
    """The joint events of a cluster, ``(E, T_c)`` int: ``1 + j`` (local measurement ``j``) or 0
    (missed), no measurement twice."""
    rows: list[tuple[int, ...]] = []

    def grow(t, used, prefix):
        if t == len(adj):
            rows.append(prefix)
            return
        grow(t + 1, used, prefix + (0,))
        for j in adj[t]:
            if j not in used:
                grow(t + 1, used | {j}, prefix + (1 + j,))

    grow(0, frozenset(), ())
    out = np.array(rows, dtype=int).reshape(-1, len(adj))
    out.setflags(write=False)
    return out


_small_cluster_events = functools.lru_cache(maxsize=1024)(_cluster_events)  # clusters of <= 256 events

# the subset programme costs O(T_c M_c 2**M_c) and holds 2 (T_c + 1) 2**M_c floats: 16 targets on 16
# measurements took 0.9 s and 20 on 20 took 27 s (and 350 MB) on the development machine under load
_DP_MAX_MEASUREMENTS = 16


def _subset_marginals(W: np.ndarray) -> tuple[np.ndarray, float]:
    r"""Exact JPDA marginals of one cluster by dynamic programming over the subsets of its
    measurements (forward-backward over the targets), without listing the joint events.

    ``W`` (T_c, 1 + M_c) holds each target's weights, column 0 missed and ``1 + j`` measurement
    ``j`` (0 outside the gate); a joint event weighs :math:`\prod_t W_{t a_t}`. With
    :math:`f_t(S)` the summed weight of the events of targets :math:`0..t-1` that use exactly the
    measurement set :math:`S` and :math:`b_t(S)` that of targets :math:`t..T_c-1` avoiding
    :math:`S`,

    .. math:: f_{t+1}(S) = W_{t0} f_t(S) + \sum_{j \in S} W_{tj} f_t(S \setminus j),\quad
       b_t(S) = W_{t0} b_{t+1}(S) + \sum_{j \notin S} W_{tj} b_{t+1}(S \cup j),

    :math:`\beta_{t0} \propto W_{t0}\sum_S f_t(S) b_{t+1}(S)` and
    :math:`\beta_{tj} \propto W_{tj}\sum_{S \not\ni j} f_t(S) b_{t+1}(S \cup j)`, both normalised
    by :math:`\sum_S f_t(S) b_t(S)`, the total weight. Cost :math:`O(T_c M_c 2^{M_c})` against the
    :math:`O(M_c^{T_c})` events. Each :math:`f_t`, :math:`b_t` is rescaled to a maximum of 1 (the
    scale cancels in each target's normalisation), so no product underflows.

    Returns ``(beta (T_c, 1 + M_c), number of joint events)``, the count being the same recursion
    with unit weights on the gated pairs (a float, exact below :math:`2^{53}`).
    """
    Tc, M = W.shape[0], W.shape[1] - 1
    S = 1 << M
    f = np.zeros((Tc + 1, S))
    b = np.ones((Tc + 1, S))
    f[0, 0] = 1.0
    cnt = np.zeros(S)
    cnt[0] = 1.0
    gated = W[:, 1:] > 0

    def add_to_with(dst, src, j, w, into_with):
        # view the subsets as (high bits, bit j, low bits): bit j is axis 1
        d, s_ = dst.reshape(-1, 2, 1 << j), src.reshape(-1, 2, 1 << j)
        if into_with:  # dst(S with j) += w src(S without j)
            d[:, 1, :] += w * s_[:, 0, :]
        else:  # dst(S without j) += w src(S with j)
            d[:, 0, :] += w * s_[:, 1, :]

    for t in range(Tc):
        g, c = W[t, 0] * f[t], cnt.copy()
        for j in np.flatnonzero(gated[t]):
            add_to_with(g, f[t], j, W[t, 1 + j], True)
            add_to_with(c, cnt, j, 1.0, True)
        top = g.max()
        f[t + 1], cnt = (g / top if top > 0 else g), c
    for t in range(Tc - 1, -1, -1):
        h = W[t, 0] * b[t + 1]
        for j in np.flatnonzero(gated[t]):
            add_to_with(h, b[t + 1], j, W[t, 1 + j], False)
        top = h.max()
        b[t] = h / top if top > 0 else h
    beta = np.zeros_like(W)
    for t in range(Tc):
        beta[t, 0] = W[t, 0] * np.dot(f[t], b[t + 1])
        for j in np.flatnonzero(gated[t]):
            fv, bv = f[t].reshape(-1, 2, 1 << j), b[t + 1].reshape(-1, 2, 1 << j)
            beta[t, 1 + j] = W[t, 1 + j] * np.sum(fv[:, 0, :] * bv[:, 1, :])
        beta[t] /= beta[t].sum()
    return beta, float(cnt.sum())


def _too_many_events(count, exact, n_targets, n_meas, b, batch, max_events):
    size = (f"{count}" if count < 10**7 else f"{count:.3g}") if exact else f"at least {count:.3g}"
    where = f" (run {tuple(int(i) for i in np.unravel_index(b, batch))})" if batch else ""
    raise ValueError(
        f"jpda_update would enumerate {size} joint events in one gating cluster of {n_targets} targets and "
        f"{n_meas} measurements{where}, above max_events = {max_events}; the exact subset programme takes "
        f"at most {_DP_MAX_MEASUREMENTS} measurements per cluster: gate tighter (smaller P_G), "
        "separate the targets, update each target with pdaf_update, assign with gnn_assignment "
        "(or Murty's k best assignments for an approximate JPDA), or raise max_events")


class JPDAUpdate(NamedTuple):
    """JPDA result for ``T`` targets: ``x`` (..., T, n), ``P`` (..., T, n, n), marginal
    association probabilities ``beta`` (..., T, M_max + 1) (column 0: missed), the per-target
    ``gates`` (a :class:`Gate` with batch axes (..., T)) and ``n_events`` (...) float, the number
    of joint events summed over the gating clusters (enumerated, or counted by the subset
    programme; an exact integer below :math:`2^{53}`)."""

    x: np.ndarray
    P: np.ndarray
    beta: np.ndarray
    gate: Gate
    n_events: np.ndarray


def jpda_update(xs, Ps, Z, H, R, *, P_D: float, P_G: float, clutter_density, mask=None,
                max_events: int = 100_000) -> JPDAUpdate:
    r"""Joint probabilistic data association with exact marginals (Fortmann, Bar-Shalom &
    Scheffe 1983), cluster by cluster: small clusters by enumerating their joint events, larger
    ones by dynamic programming over the subsets of their measurements.

    A joint event gives each target one gated measurement or none, no measurement to two
    targets; its probability is proportional to
    :math:`\prod_{t\,\text{missed}}(1 - P_D P_G)\prod_{t \to j} P_D N(\nu_{tj}; 0, S_t)/\lambda`.
    The marginals :math:`\beta_{tj}` then drive a PDAF-form update of each target. The targets
    split into **gating clusters** (targets linked through shared gated measurements); the events
    are products of independent events of the clusters, so each cluster is enumerated alone and
    the marginals are exact. A cluster whose events number at most
    :math:`\prod_t (1 + m_t) \le 256` (``m_t`` the gated measurements of target ``t``) is
    enumerated; a larger one with at most 16 measurements goes to the forward-backward programme over the subsets
    of its measurements (``_subset_marginals``, :math:`O(T_c M_c 2^{M_c})`: 12 targets gating the
    same 12 measurements, :math:`5.3\times10^{10}` events, take about 0.02 s); a cluster of
    more than 16 measurements is enumerated if it has at most ``max_events`` events.

    Parameters
    ----------
    xs : (..., T, n) predicted states; ``Ps`` (..., T, n, n).
    Z : (..., M_max, m) padded scan shared by the targets; ``mask`` (..., M_max).
    H, R : as in :func:`pdaf_update`; ``clutter_density`` the parametric :math:`\lambda > 0`.
    max_events : the largest number of joint events to enumerate in a cluster of more than 16
        measurements (beyond the subset programme). The count grows like :math:`M^T`; above
        ``max_events`` a ``ValueError`` gives the count and what to do instead. The default,
        :math:`10^5`, enumerates in a fraction of a second (0.3 s on the development machine;
        :math:`1.4\times10^6` events took 3.7 s).

    Notes
    -----
    Python loops over the runs ``...`` and the clusters (the clusters differ between runs); the
    enumeration of a small cluster's events is cached by its gating pattern.
    """
    P_D, P_G, lam = _check_prob_detect(P_D), _check_prob_gate(P_G), _check_density(clutter_density)
    if lam is None or np.any(lam <= 0):
        raise ValueError(f"clutter_density must be > 0 for JPDA, got {clutter_density!r}")
    if isinstance(max_events, bool) or int(max_events) != max_events or max_events < 1:
        raise ValueError(f"max_events must be a positive integer, got {max_events!r}")
    xs = as_vector(xs, "xs")
    if xs.ndim < 2:
        raise ValueError(f"xs must have shape (..., T, n), got shape {xs.shape}")
    x, P, Zc, mask, H, R = _check_filter_args(xs, Ps, Z, mask, H, R)
    return _jpda_update(x, P, Zc, mask, H, R, P_D, P_G, lam, max_events)


def _jpda_update(x, P, Zc, mask, H, R, P_D, P_G, lam, max_events) -> JPDAUpdate:
    """Kernel of :func:`jpda_update` on checked arguments (no checks here): ``x`` (..., T, n),
    ``P`` (..., T, n, n), ``Zc`` (..., M, m) finite (zero at padding), ``mask`` (..., M) bool,
    ``H``, ``R`` checked, ``P_D``, ``P_G`` floats, ``lam`` > 0 (scalar or array over ``...``),
    ``max_events`` a positive integer. Raises the ``max_events`` ``ValueError`` of
    :func:`jpda_update` (callers may catch it and fall back on an approximation)."""
    T, M = x.shape[-2], Zc.shape[-2]
    g, u = _gate(x, P, Zc[..., None, :, :], mask[..., None, :], H, R, P_G)
    logL0, logL, _, _ = _log_pda_terms(g, P_D, P_G, np.asarray(lam)[..., None])
    table = np.concatenate([logL0[..., None], logL], axis=-1)  # (..., T, M + 1)
    batch = table.shape[:-2]
    table = table.reshape((-1, T, M + 1))
    inside = np.broadcast_to(g.inside, batch + (T, M)).reshape((-1, T, M))
    # runs where no measurement is in two gates: every target is its own cluster, whose events
    # are "missed" or one gated measurement, so its marginals are its own normalised weights
    beta = np.exp(table - _logsumexp(table)[..., None])
    n_events = np.where(inside.any(-1), 1 + inside.sum(-1), 0).sum(-1).astype(float)
    big = np.where(inside.sum(-1) > _DP_MAX_MEASUREMENTS, inside.sum(-1), 0)  # lone targets beyond the programme
    if max_events < 1 + big.max(initial=0):  # (only a tiny max_events: a cluster of one target)
        b, t = np.unravel_index(np.argmax(big), inside.shape[:2])
        _too_many_events(1 + int(inside[b, t].sum()), True, 1, int(inside[b, t].sum()), b, batch, max_events)
    for b in np.flatnonzero((inside.sum(-2) > 1).any(-1)):
        beta[b] = 0.0
        beta[b, :, 0] = 1.0  # targets outside every cluster: missed
        n_events[b] = 0
        for ts, js in _gating_clusters(inside[b]):
            local = {int(j): k for k, j in enumerate(js)}
            adj = tuple(tuple(local[int(j)] for j in np.flatnonzero(inside[b, t])) for t in ts)
            cols_all = np.concatenate([[0], 1 + js])  # local column -> column of table
            if np.prod([1.0 + len(a) for a in adj]) > 256 and len(js) <= _DP_MAX_MEASUREMENTS:
                sub = table[b][ts[:, None], cols_all[None, :]]  # (T_c, 1 + M_c)
                bl, count = _subset_marginals(np.exp(sub - sub.max(-1, keepdims=True)))
                beta[b, ts[:, None], cols_all[None, :]] = bl
                n_events[b] += count
                continue
            count, exact = _count_events(adj, int(max_events))
            if count > max_events:
                _too_many_events(count, exact, len(ts), len(js), b, batch, max_events)
            ev = (_small_cluster_events if count <= 256 else _cluster_events)(adj)  # (E, T_c), local
            cols = cols_all[ev]  # (E, T_c), columns of table
            logw = table[b, ts[None, :], cols].sum(-1)
            w = np.exp(logw - _logsumexp(logw))
            for k, t in enumerate(ts):
                beta[b, t] = np.bincount(cols[:, k], weights=w, minlength=M + 1)
            n_events[b] += len(ev)
    beta = beta.reshape(batch + (T, M + 1))
    xp, Pp, _ = _pda_combine(x, P, u, g.nu, beta)
    return JPDAUpdate(xp, Pp, beta, g, n_events.reshape(batch))


# --------------------------------------------------------------------------------------------
# metrics on sets
# --------------------------------------------------------------------------------------------
class GOSPA(NamedTuple):
    """GOSPA distance (alpha = 2) and its parts: ``localisation`` (sum of ``d**p`` over the
    assigned pairs), ``missed`` and ``false`` counts, so that
    ``distance**p = localisation + c**p / 2 * (missed + false)``."""

    distance: float
    localisation: float
    missed: int
    false: int


def _check_sets(X, Y, c, p):
    X = np.atleast_2d(as_float_array(X, "truth")) if np.size(X) else np.zeros((0, np.shape(Y)[-1] if np.size(Y) else 1))
    Y = np.atleast_2d(as_float_array(Y, "estimate")) if np.size(Y) else np.zeros((0, X.shape[-1]))
    if X.ndim != 2 or Y.ndim != 2 or X.shape[1] != Y.shape[1]:
        raise ValueError(f"truth and estimate must be sets of points (N, d) and (M, d) of the same width d, "
                         f"got shapes {X.shape} and {Y.shape}")
    check_finite(X, "truth")
    check_finite(Y, "estimate")
    if not (np.isfinite(c) and c > 0):
        raise ValueError(f"c (cut-off distance) must be finite and > 0, got {c!r}")
    if not (np.isfinite(p) and p >= 1):
        raise ValueError(f"p (order) must be >= 1, got {p!r}")
    return X, Y


def gospa(truth, estimate, *, c: float, p: float = 2.0) -> GOSPA:
    r"""Generalized OSPA with :math:`\alpha = 2` (Rahmathullah, García-Fernández & Svensson 2017):

    .. math:: d^{(c,2)}_p(X, Y) = \Big(\min_\gamma \sum_{(i,j)\in\gamma} d(x_i, y_j)^p
       + \tfrac{c^p}{2}(|X| + |Y| - 2|\gamma|)\Big)^{1/p},

    over partial assignments :math:`\gamma` of pairs closer than ``c`` (Euclidean ``d``).

    Parameters
    ----------
    truth : (N, d) true points; ``estimate`` (M, d) estimated points (either may be empty).
    c : cut-off distance; ``p`` the order (>= 1).

    Examples
    --------
    >>> from kftrack.association import gospa
    >>> g = gospa([[0.0, 0.0], [10.0, 0.0]], [[0.0, 1.0]], c=5.0, p=2.0)   # one target found 1 m off, one missed
    >>> round(g.distance, 6), g.localisation, g.missed, g.false       # sqrt(1 + 5²/2)
    (3.674235, 1.0, 1, 0)
    """
    X, Y = _check_sets(truth, estimate, c, p)
    return _gospa(X, Y, c, p)[0]


def gospa_assignment(truth, estimate, *, c: float, p: float = 2.0) -> tuple[GOSPA, np.ndarray]:
    r""":func:`gospa` and its optimal assignment: ``(GOSPA, pairs)``, ``pairs`` (k, 2) int, each
    row ``(i, j)`` a truth ``i`` matched to estimate ``j`` at distance below ``c`` (the
    :math:`\gamma` of :func:`gospa`, ``k = N - missed = M - false``), sorted by ``i``.

    Examples
    --------
    >>> from kftrack.association import gospa_assignment
    >>> g, pairs = gospa_assignment([[0.0, 0.0], [10.0, 0.0]], [[10.0, 1.0]], c=5.0)
    >>> pairs.tolist(), g.missed
    ([[1, 0]], 1)
    """
    X, Y = _check_sets(truth, estimate, c, p)
    return _gospa(X, Y, c, p)


def _gospa(X, Y, c, p):
    """Kernel of :func:`gospa` and :func:`gospa_assignment` (checked sets)."""
    N, M = len(X), len(Y)
    if N == 0 or M == 0:
        return GOSPA(float((c**p / 2.0 * (N + M)) ** (1.0 / p)), 0.0, N, M), np.zeros((0, 2), dtype=int)
    D = np.linalg.norm(X[:, None, :] - Y[None, :, :], axis=-1)
    C = np.minimum(D, c) ** p
    rows, cols = linear_sum_assignment(C)
    keep = D[rows, cols] < c
    loc = float(np.sum(D[rows, cols][keep] ** p))
    n_pairs = int(keep.sum())
    missed, false = N - n_pairs, M - n_pairs
    pairs = np.stack([rows[keep], cols[keep]], axis=1).astype(int)
    return GOSPA(float((loc + c**p / 2.0 * (missed + false)) ** (1.0 / p)), loc, missed, false), pairs


def ospa(truth, estimate, *, c: float, p: float = 2.0) -> float:
    r"""OSPA distance (Schuhmacher, Vo & Vo 2008), for :math:`n = \max(|X|, |Y|) > 0`:
    :math:`\big(\frac1n[\min_\pi\sum_i \min(d, c)^p + c^p\,|\,|X|-|Y|\,|]\big)^{1/p}`; 0 for two
    empty sets. Arguments as in :func:`gospa`."""
    X, Y = _check_sets(truth, estimate, c, p)
    N, M = len(X), len(Y)
    n = max(N, M)
    if n == 0:
        return 0.0
    if min(N, M) == 0:
        return float(c)
    C = np.minimum(np.linalg.norm(X[:, None, :] - Y[None, :, :], axis=-1), c) ** p
    rows, cols = linear_sum_assignment(C)
    return float(((C[rows, cols].sum() + c**p * abs(N - M)) / n) ** (1.0 / p))


# --------------------------------------------------------------------------------------------
# drivers over a scan sequence
# --------------------------------------------------------------------------------------------
class ScanFilterResult(NamedTuple):
    """A filtered scan sequence, time first: predictions ``x_prior`` (T, ..., n), ``P_prior``
    (T, ..., n, n) (``x_prior[0] = x0``), estimates ``x``, ``P`` and ``n_gated`` (T, ...), the
    number of measurements in each gate."""

    x_prior: np.ndarray
    P_prior: np.ndarray
    x: np.ndarray
    P: np.ndarray
    n_gated: np.ndarray


_METHODS = ("nn", "snn", "pdaf")


def _check_motion(F, Q, n):
    """The transition ``F`` (n, n) and process-noise covariance ``Q`` (n, n) of one scan interval."""
    F = as_float_array(F, "F")
    if F.shape != (n, n):
        raise ValueError(f"F must have shape ({n}, {n}) (n = {n} from x0), got shape {F.shape}")
    return F, check_covariance(Q, "Q", n, origin=f"n = {n} from x0")


def _predict(x, P, F, Q):
    """One scan's prediction, ``x`` (..., n), ``P`` (..., n, n); the covariance kept symmetric."""
    x, P = (F @ x[..., None])[..., 0], F @ P @ F.T + Q
    return x, 0.5 * (P + np.swapaxes(P, -1, -2))


def _scan_parts(scan):
    Z, mask = scan[0], scan[1]
    amp = getattr(scan, "amplitude", None)
    return Z, mask, amp


def filter_scans(method: str, scans, x0, P0, F, Q, H, R, *, P_G: float, P_D: float = 1.0,
                 clutter_density=None) -> ScanFilterResult:
    r"""Track one target through a sequence of padded scans with one association method.

    Parameters
    ----------
    method : ``"nn"`` (nearest neighbour), ``"snn"`` (strongest neighbour: the scans must carry
        ``amplitude``, as :class:`kftrack.clutter.Scans` do) or ``"pdaf"``.
    scans : sequence of T scans, each ``(Z, mask, ...)`` with ``Z`` (..., M_k, m) (e.g. the
        :class:`kftrack.clutter.Scans` of each scan); ``M_k`` may differ between scans.
    x0 : (..., n) prediction for the first scan; ``P0`` (..., n, n).
    F, Q : (n, n) transition and process-noise covariance of one scan interval.
    H, R : (m, n), (m, m) the measurement.
    P_G, P_D, clutter_density : as in :func:`pdaf_update` (``P_D`` and ``clutter_density`` used
        by the PDAF only).
    """
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
    x, P = as_vector(x0, "x0"), check_covariance(P0, "P0")
    F, Q = _check_motion(F, Q, x.shape[-1])
    out = {k: [] for k in ScanFilterResult._fields}
    for k, scan in enumerate(scans):
        if k:
            x, P = _predict(x, P, F, Q)
        out["x_prior"].append(x)
        out["P_prior"].append(P)
        Z, mask, amp = _scan_parts(scan)
        if method == "nn":
            u = nearest_neighbour(x, P, Z, H, R, P_G=P_G, mask=mask)
        elif method == "snn":
            if amp is None:
                raise ValueError("method 'snn' needs scans that carry an amplitude (kftrack.clutter.Scans)")
            u = strongest_neighbour(x, P, Z, H, R, amp, P_G=P_G, mask=mask)
        else:
            u = pdaf_update(x, P, Z, H, R, P_D=P_D, P_G=P_G, clutter_density=clutter_density, mask=mask)
        x, P = u.x, u.P
        out["x"].append(x)
        out["P"].append(np.broadcast_to(P, x.shape + x.shape[-1:]))
        out["n_gated"].append(u.gate.inside.sum(-1))
    out["P_prior"] = [np.broadcast_to(p, a.shape + a.shape[-1:]) for p, a in zip(out["P_prior"], out["x_prior"])]
    return ScanFilterResult(*(np.stack(out[k]) for k in ScanFilterResult._fields))


def jpda_filter(scans, x0, P0, F, Q, H, R, *, P_G: float, P_D: float, clutter_density):
    """Track ``T`` targets with :func:`jpda_update` through a scan sequence.

    ``x0`` (..., T, n), ``P0`` (..., T, n, n); other arguments as in :func:`filter_scans`.
    Returns the estimates ``x`` (K, ..., T, n) and ``P`` (K, ..., T, n, n) for the K scans."""
    x, P = as_vector(x0, "x0"), check_covariance(P0, "P0")
    F, Q = _check_motion(F, Q, x.shape[-1])
    xs, Ps = [], []
    for k, scan in enumerate(scans):
        if k:
            x, P = _predict(x, P, F, Q)
        u = jpda_update(x, P, scan[0], H, R, P_G=P_G, P_D=P_D, clutter_density=clutter_density, mask=scan[1])
        x, P = u.x, u.P
        xs.append(x)
        Ps.append(P)
    return np.stack(xs), np.stack(Ps)


def gnn_filter(scans, x0, P0, F, Q, H, R, *, P_G: float):
    r"""Track ``T`` targets with global nearest neighbour through a scan sequence: per scan and
    run, :func:`gnn_assignment` with cost :math:`d^2 + \log|S_i|` on the gated pairs and, for a
    track left without a measurement, the cost of its gate's edge :math:`\gamma + \log|S_i|`;
    then a Kalman update of each assigned track (the prediction for the others).

    ``x0`` (N, T, n) for N runs (one batch axis), ``P0`` (N, T, n, n). **The assignment
    is a Python loop over the runs** (``linear_sum_assignment`` solves one problem at a time, so
    its cost grows linearly with N); gating
    and updates are vectorised over runs. Returns ``x`` (K, N, T, n), ``P`` (K, N, T, n, n)."""
    x, P = as_vector(x0, "x0"), check_covariance(P0, "P0")
    if x.ndim != 3:
        raise ValueError(f"x0 must have shape (runs, T, n), got shape {x.shape}")
    n = x.shape[-1]
    F, Q = _check_motion(F, Q, n)
    H, R = _check_measurement(H, R, n, f"n = {n} from x0")
    P_G = _check_prob_gate(P_G)
    xs, Ps = [], []
    for k, scan in enumerate(scans):
        if k:
            x, P = _predict(x, P, F, Q)
        Z, mask = check_scan(scan[0], scan[1], H.shape[-2])
        g, u = _gate(x, P, Z[:, None], mask[:, None], H, R, P_G)
        logdet = np.linalg.slogdet(g.S)[1]
        cost, edge = g.d2 + logdet[..., None], g.gamma + logdet  # edge: the cost on each track's gate
        idx = np.stack([gnn_assignment(cost[r], g.inside[r], edge[r]) for r in range(x.shape[0])])
        upd = _select_update(x, P, g, u, idx)
        x, P = upd.x, upd.P
        xs.append(x)
        Ps.append(P)
    return np.stack(xs), np.stack(Ps)
